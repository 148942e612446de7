"""Resuming is exact: a run interrupted at a step and resumed is the uninterrupted run, its
metrics cover every session, and a checkpoint of another run (camera, data, model) or a
checkpoint file that cannot be read is refused before any work, with one line."""
from __future__ import annotations

import json
import shutil
import signal

import lightning as L
import pytest
import torch

from segs.config import user_errors_exit
from segs.train import build, run

# 200 steps: anchor growth (random, from torch's RNG) runs at steps 100 and 200, after the resume
STEPS = ["trainer.max_steps=200", "callbacks.periodic_checkpoint.every_n_steps=0", "eval.progress=false"]


class SignalAt(L.Callback):
    """Sends SIGINT to this process at the end of `step` (as a user's Ctrl-C would)."""

    def __init__(self, step: int):
        self.step = step

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        if trainer.global_step == self.step:
            signal.raise_signal(signal.SIGINT)


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    """(config factory, metrics, run folder) of one uninterrupted 200-step tiny run."""
    from conftest import TINY
    from segs.config import compose

    out = tmp_path_factory.mktemp("uninterrupted")
    make = lambda *o, out: compose(TINY + STEPS + list(o), output_dir=str(out))  # noqa: E731
    return make, run(make(out=out)), out


@pytest.mark.slow
def test_a_run_interrupted_at_a_step_and_resumed_is_the_uninterrupted_run(uninterrupted, tmp_path):
    make, whole, _ = uninterrupted
    out = tmp_path / "resumed"
    with pytest.raises(SystemExit) as stop:
        run(make("+callbacks.signal_at._target_=test_resume.SignalAt", "+callbacks.signal_at.step=40", out=out))
    assert stop.value.code == 130
    ckpt = out / "checkpoints" / "last.ckpt"
    first = torch.load(ckpt, weights_only=False)
    assert 40 <= first["global_step"] < 100  # before the first anchor growth
    resumed = run(make(f"ckpt_path={ckpt}", out=out))
    # the same anchors (growth draws from the restored RNG) and, up to the CPU backward's summation
    # order over 2 threads, the same images
    assert resumed["anchors"] == whole["anchors"] and resumed["keyframes"] == whole["keyframes"]
    assert resumed["psnr"] == pytest.approx(whole["psnr"], abs=0.05)
    # the metrics cover both sessions, not the last one
    assert resumed["iterations"] == 200 and resumed["sessions"] == 2
    assert resumed["mapping_time_s"] > first["segs_run"]["fit_s"] and resumed["wall_time_s"] > first["segs_run"]["wall_s"]
    assert resumed["tracking_fps"] is not None and resumed["iteration_ms_median"] is not None
    assert len(torch.load(out / "checkpoints" / "final.ckpt", weights_only=False)["segs_run"]["iteration_ms"]) == 200


# the ORB frontend on 16 synthetic frames, fed over 160 steps of a 120-step run: interrupted at
# step 40 with frames still to track, and training ends before the sequence does
ORB = ["+experiment=synthetic", "data.n_frames=16", "data.width=320", "data.height=240", "data.trajectory=orbit",
       "data.speed=0.2", "trainer.max_steps=120", "callbacks.slam_bridge.frames_per_step=0.1",
       "callbacks.slam_bridge.min_initial_keyframes=2", "callbacks.periodic_checkpoint.every_n_steps=0", "eval.save_renders=0",
       "eval.write_ply=false", "eval.progress=false", "logger=none", "callbacks.slam_bridge.progress=false",
       "~callbacks.progress_bar", "trainer.enable_progress_bar=false"]  # fmt: skip


@pytest.mark.slow
def test_an_orb_run_interrupted_mid_sequence_and_resumed_is_the_uninterrupted_run(tmp_path):
    from segs.config import compose

    make = lambda *o, out: compose(ORB + list(o), output_dir=str(out))  # noqa: E731
    whole = run(make(out=tmp_path / "whole"))
    out = tmp_path / "resumed"
    with pytest.raises(SystemExit):
        run(make("+callbacks.signal_at._target_=test_resume.SignalAt", "+callbacks.signal_at.step=40", out=out))
    ckpt = out / "checkpoints" / "last.ckpt"
    from conftest import instances_in

    saved = torch.load(ckpt, weights_only=False)["callbacks"]["SlamBridge"]["run"]
    assert 2 < saved["source"]["cursor"] < 16 and saved["source"]["frontend"]["kind"] == "orb"  # mid-sequence
    assert not instances_in(saved)
    resumed = run(make(f"ckpt_path={ckpt}", out=out))
    for name in ("trajectory.txt", "map_points.ply"):
        assert (out / name).read_bytes() == (tmp_path / "whole" / name).read_bytes(), name
    assert resumed["keyframes"] == whole["keyframes"] and resumed["training_views"] == whole["training_views"]
    assert resumed["anchors"] == whole["anchors"] and resumed["psnr"] == pytest.approx(whole["psnr"], abs=0.05)


def test_metrics_of_a_run_resumed_from_its_final_checkpoint_describe_the_whole_run(uninterrupted, tmp_path):
    make, whole, out = uninterrupted
    again = run(make(f"ckpt_path={out / 'checkpoints' / 'final.ckpt'}", out=tmp_path / "again"))
    assert again["iterations"] == whole["iterations"] == 200 and again["anchors"] == whole["anchors"]
    assert again["mapping_time_s"] >= whole["mapping_time_s"]  # not the ~0 s of fitting nothing
    assert again["iterations_per_s"] <= whole["iterations_per_s"] * 1.001
    assert again["tracking_fps"] == pytest.approx(whole["tracking_fps"])  # kept, not null


def _refused(cfg, capsys) -> str:
    with pytest.raises(SystemExit) as exc:
        with user_errors_exit():
            build(cfg)
    assert exc.value.code == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and err[0].startswith("error: ckpt_path="), err
    return err[0]


@pytest.mark.parametrize("override,named", [("sensor=mono", "sensor"), ("data.n_frames=15", "sequence"),
                                            ("data.width=128", "camera"), ("model=plain_3dgs", "model"),
                                            ("model.feature_dim=16", "model architecture"),
                                            ("eval.holdout_every=4", "eval.holdout_every")])  # fmt: skip
def test_a_checkpoint_of_another_camera_data_or_model_is_refused(uninterrupted, tmp_path, capsys, override, named):
    make, _, out = uninterrupted
    msg = _refused(make(f"ckpt_path={out / 'checkpoints' / 'final.ckpt'}", override, out=tmp_path), capsys)
    assert f"with {named} " in msg


def test_a_checkpoint_file_that_cannot_be_read_is_refused(uninterrupted, tmp_path, capsys):
    make, _, out = uninterrupted
    assert "not found" in _refused(make(f"ckpt_path={tmp_path / 'nope.ckpt'}", out=tmp_path), capsys)
    assert "is a folder" in _refused(make(f"ckpt_path={out}", out=tmp_path), capsys)
    cut = tmp_path / "cut.ckpt"
    data = (out / "checkpoints" / "final.ckpt").read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    assert "truncated or corrupt" in _refused(make(f"ckpt_path={cut}", out=tmp_path), capsys)
    other = tmp_path / "other.ckpt"
    torch.save({"weights": torch.zeros(2)}, other)
    assert "not a segs checkpoint" in _refused(make(f"ckpt_path={other}", out=tmp_path), capsys)


def test_resumed_in_its_own_folder_the_old_result_is_kept_aside(uninterrupted, tmp_path):
    make, whole, out = uninterrupted
    folder = tmp_path / "copy"
    shutil.copytree(out, folder)
    from segs.run_folder import claim, release

    claim(folder, str(folder / "checkpoints" / "final.ckpt"))
    release(folder)
    assert not (folder / "metrics.json").exists()
    assert json.loads((folder / "metrics.previous.json").read_text())["psnr"] == whole["psnr"]


def test_plain_3dgs_resumes_to_the_same_gaussians(tmp_path):
    # densification (clone / split / prune: rows, moments and statistics of the Gaussians' store)
    # runs at step 100, after the resume from step 40
    from conftest import TINY
    from segs.config import compose

    extra = ["+ablation=plain_3dgs", "trainer.max_steps=120", "model.densify.until_step=30000", "eval.save_renders=0"]
    make = lambda *o, out: compose(TINY + STEPS[1:] + extra + list(o), output_dir=str(out))  # noqa: E731
    whole = run(make(out=tmp_path / "whole"))
    out = tmp_path / "resumed"
    with pytest.raises(SystemExit):
        run(make("+callbacks.signal_at._target_=test_resume.SignalAt", "+callbacks.signal_at.step=40", out=out))
    resumed = run(make(f"ckpt_path={out / 'checkpoints' / 'last.ckpt'}", out=out))
    assert resumed["gaussians"] == whole["gaussians"] and resumed["iterations"] == 120
    assert resumed["psnr"] == pytest.approx(whole["psnr"], abs=0.05)
