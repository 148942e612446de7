"""metrics.json and tracking.json say how they were made; a ground-truth-pose run has no ATE."""
from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path

from segs.config import compose
from segs.provenance import git_state, provenance
from segs.track import run as track
from segs.train import run as train

KEYS = {"frontend", "slam_mode", "sensor", "raster_backend", "device", "threads", "seed", "overrides", "segs_version",
        "git_commit", "git_dirty", "versions", "machine"}


def _check_common(p: dict) -> None:
    assert KEYS <= set(p), KEYS - set(p)
    assert p["segs_version"] and p["versions"]["torch"] and p["versions"]["numpy"]
    assert p["machine"]["cores"] >= 1 and p["machine"]["cpu"]
    if p["git_commit"] is not None:  # run from a checkout
        assert re.fullmatch(r"[0-9a-f]{40}", p["git_commit"]) and isinstance(p["git_dirty"], bool)


def test_a_training_run_records_how_it_was_made_and_no_ate_for_ground_truth_poses(tiny_cfg, capsys):
    cfg = tiny_cfg("trainer.max_steps=20", "seed=3", "callbacks.periodic_checkpoint.every_n_steps=0", "eval.write_ply=false")
    train(cfg)
    m = json.loads((Path(cfg.paths.output_dir) / "metrics.json").read_text())
    p = m["provenance"]
    _check_common(p)
    assert p["frontend"] == "known_poses" and p["sensor"] == "rgbd" and p["seed"] == 3
    assert p["raster_backend"] in ("cpu", "torch") and p["device"] == "cpu"
    assert p["compiled_step_code"] is False  # mapping.compile=null: compiled on a CUDA device only
    assert p["threads"]["torch"] >= 1
    assert "seed=3" in p["overrides"] and "trainer.max_steps=20" in p["overrides"]
    # the known-poses frontend replays the ground truth: ATE is not measured, never a 0.00 cm
    assert m["ate_rmse_m"] is None and m["ate"]["reason"] == "ground-truth poses" and "known_poses" in m["ate_note"]
    out = capsys.readouterr().out
    assert "ATE RMSE n/a (ground-truth poses)" in out and "0.00 cm" not in out


def test_a_tracking_run_records_how_it_was_made(tmp_path):
    cfg = compose(["+experiment=synthetic", "data.n_frames=8", "data.width=320", "data.height=240", "data.trajectory=orbit",
                   "data.speed=0.2"], output_dir=str(tmp_path))  # fmt: skip
    track(cfg, progress=False)
    saved = json.loads((tmp_path / "tracking.json").read_text())
    p = saved["provenance"]
    _check_common(p)
    assert p["frontend"] == "orb" and p["sensor"] == "rgbd" and p["raster_backend"] is None and p["device"] is None
    assert saved["ate_rmse_m"] is not None  # an estimate: scored


def test_tracking_with_ground_truth_poses_reports_ate_not_applicable(tmp_path, capsys):
    cfg = compose(["+experiment=synthetic", "slam=known_poses", "data.n_frames=6", "data.width=96", "data.height=72"],
                  output_dir=str(tmp_path))  # fmt: skip
    track(cfg, progress=False)
    saved = json.loads((tmp_path / "tracking.json").read_text())
    assert saved["ate_rmse_m"] is None and saved["ate"]["reason"] == "ground-truth poses"
    assert saved["provenance"]["frontend"] == "known_poses"
    assert "n/a (ground-truth poses)" in capsys.readouterr().out


def test_git_state_reads_commit_and_dirty_flag_and_is_none_outside_a_checkout(tmp_path):
    assert git_state.__wrapped__(tmp_path) == {"commit": None, "dirty": None}
    git = ["git", "-c", "user.name=t", "-c", "user.email=t@t", "-C", str(tmp_path)]
    subprocess.run(["git", "init", "-q", str(tmp_path)], check=True)
    (tmp_path / "a.txt").write_text("1")
    subprocess.run(git + ["add", "a.txt"], check=True)
    subprocess.run(git + ["commit", "-qm", "a"], check=True)
    clean = git_state.__wrapped__(tmp_path)
    assert re.fullmatch(r"[0-9a-f]{40}", clean["commit"]) and clean["dirty"] is False
    (tmp_path / "a.txt").write_text("2")
    assert git_state.__wrapped__(tmp_path)["dirty"] is True


def test_provenance_names_an_unknown_frontend_by_its_class_path(tiny_cfg):
    cfg = tiny_cfg()
    cfg.slam._target_ = "my.package.MyFrontend"
    p = provenance(cfg, "mono")
    assert p["frontend"] == "my.package.MyFrontend" and p["sensor"] == "mono" and p["raster_backend"] is None


def test_a_run_without_a_test_view_says_why(tiny_cfg, capsys):
    # every frame a keyframe and none held out: nothing left to test on (a sparse keyframe sequence)
    cfg = tiny_cfg("trainer.max_steps=10", "slam.keyframe_every=1", "eval.holdout_every=0", "callbacks.periodic_checkpoint.every_n_steps=0",
                   "eval.write_ply=false")  # fmt: skip
    train(cfg)
    m = json.loads((Path(cfg.paths.output_dir) / "metrics.json").read_text())
    assert m["test_views"] == 0 and m["psnr"] is None and "eval.holdout_every" in m["test_note"]
    out = capsys.readouterr().out
    assert "test views 0: no test view: every tracked frame was trained on" in out and "n/a dB" not in out
    assert "renders/" not in out and not (Path(cfg.paths.output_dir) / "renders").exists()  # nothing written there: not listed
