"""The bad-input catalogue (docs/reliability.md): one line naming the file or key, exit 2,
no traceback, and no metrics.json (nothing that looks like a finished result); a frontend that
maps nothing leaves a metrics.json with status "tracking_failed" and no image metric."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from segs.config import REPO_ROOT, compose, user_errors_exit
from segs.train import run

SAMPLE = REPO_ROOT / "datasets" / "tum_fr3_cabinet_kf"
FAST = ["data.downscale=4", "trainer.max_steps=5", "logger=none", "callbacks.slam_bridge.progress=false",
        "~callbacks.progress_bar", "trainer.enable_progress_bar=false", "slam=known_poses", "eval.progress=false"]  # fmt: skip


def _copy(tmp_path: Path, n: int = 12) -> Path:
    """The first n frames of the bundled sample (index files cut to match)."""
    root = tmp_path / "rgbd_dataset_freiburg3_copy"
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    for name in ("rgb.txt", "depth.txt", "groundtruth.txt"):
        lines = (SAMPLE / name).read_text().splitlines()
        head = [line for line in lines if line.startswith("#")]
        body = [line for line in lines if line and not line.startswith("#")][:n]
        (root / name).write_text("\n".join(head + body) + "\n")
        if name != "groundtruth.txt":
            for line in body:
                rel = line.split()[1]
                shutil.copy(SAMPLE / rel, root / rel)
    return root


def _exits_2_with_one_line(cfg, capsys) -> str:
    """Run cfg as the entry point does; it must exit 2 with one 'error: ' line and no traceback."""
    with pytest.raises(SystemExit) as exc:
        with user_errors_exit():
            run(cfg)
    assert exc.value.code == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and err[0].startswith("error: "), err
    assert "Traceback" not in err[0]
    return err[0]


def _fails(tmp_path, capsys, *overrides: str) -> str:
    out = tmp_path / "run"
    msg = _exits_2_with_one_line(compose(FAST + list(overrides), output_dir=str(out)), capsys)
    assert not (out / "metrics.json").exists()
    return msg


def _index_line(root: Path, name: str, i: int) -> tuple[int, list[str]]:
    lines = (root / name).read_text().splitlines()
    rows = [k for k, line in enumerate(lines) if line and not line.startswith("#")]
    return rows[i], lines


def test_missing_dataset_folder(tmp_path, capsys):
    msg = _fails(tmp_path, capsys, f"data.root={tmp_path / 'nope'}")
    assert str(tmp_path / "nope") in msg


def test_index_file_naming_a_missing_image(tmp_path, capsys):
    root = _copy(tmp_path)
    (root / "rgb" / "0003_rgb_raw.jpg").unlink()
    msg = _fails(tmp_path, capsys, f"data.root={root}")
    assert "0003_rgb_raw.jpg" in msg


def test_corrupt_image(tmp_path, capsys):
    root = _copy(tmp_path)
    (root / "rgb" / "0002_rgb_raw.jpg").write_bytes(b"not a jpeg at all")
    msg = _fails(tmp_path, capsys, f"data.root={root}")
    assert "0002_rgb_raw.jpg" in msg


def test_depth_of_another_size(tmp_path, capsys):
    root = _copy(tmp_path)
    cv2.imwrite(str(root / "depth" / "0001_depth_raw.png"), np.zeros((100, 120), np.uint16))
    msg = _fails(tmp_path, capsys, f"data.root={root}")
    assert "0001_depth_raw.png" in msg


def test_timestamps_that_do_not_associate(tmp_path, capsys):
    root = _copy(tmp_path)
    lines = (root / "depth.txt").read_text().splitlines()
    shifted = [f"{float(line.split()[0]) + 5.0:.4f} {line.split()[1]}" if line and not line.startswith("#") else line for line in lines]
    (root / "depth.txt").write_text("\n".join(shifted) + "\n")
    msg = _fails(tmp_path, capsys, f"data.root={root}")
    assert "depth.txt" in msg or "rgb.txt" in msg


@pytest.mark.parametrize("bad", ["0.5 0.9 0.9 0.9 0.9", "nan 0 0 0 1"])  # tz qx qy qz qw
def test_bad_ground_truth(tmp_path, capsys, bad):
    root = _copy(tmp_path)
    k, lines = _index_line(root, "groundtruth.txt", 2)
    parts = lines[k].split()
    lines[k] = " ".join(parts[:1] + parts[1:3] + bad.split())
    (root / "groundtruth.txt").write_text("\n".join(lines) + "\n")
    msg = _fails(tmp_path, capsys, f"data.root={root}")
    assert "groundtruth.txt" in msg


def test_empty_sequence(tmp_path, capsys):
    root = _copy(tmp_path)
    for name in ("rgb.txt", "depth.txt"):
        (root / name).write_text("# nothing here\n")
    msg = _fails(tmp_path, capsys, f"data.root={root}")
    assert "rgb.txt" in msg or str(root) in msg


def test_camera_the_dataset_cannot_provide(tmp_path, capsys):
    root = _copy(tmp_path)
    (root / "depth.txt").unlink()
    msg = _fails(tmp_path, capsys, f"data.root={root}", "sensor=rgbd")
    assert "rgbd" in msg and "depth" in msg
    msg = _fails(tmp_path, capsys, "sensor=stereo")
    assert "stereo" in msg


@pytest.mark.parametrize("override,key", [("model.voxel_size=-0.001", "model.voxel_size"), ("model.k=0", "model.k"),
                                          ("model.lr.offsets=-0.1", "model.lr.offsets"), ("data.downscale=0", "data.downscale"),
                                          ("trainer.max_steps=-5", "trainer.max_steps")])  # fmt: skip
def test_out_of_range_values(tmp_path, capsys, override, key):
    assert key in _fails(tmp_path, capsys, override)


def test_images_too_small_for_any_map_point(tmp_path, capsys):
    # 80x60: ORB finds no keypoint, so the keyframes carry no 3D point. Exit 2 with one line, and
    # a metrics.json that says so (status tracking_failed, no image metric), never a "finished" run
    out = tmp_path / "run"
    cfg = compose([o for o in FAST if not o.startswith("data.downscale")] + ["data.downscale=8"], output_dir=str(out))
    assert _exits_2_with_one_line(cfg, capsys).startswith("error: data: the frontend gave no 3D point")
    m = json.loads((out / "metrics.json").read_text())
    assert m["status"] == "tracking_failed" and m["psnr"] is None and m["gaussians"] == 0


def _truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def test_truncated_jpeg_is_refused_by_train_and_track(tmp_path, capsys):
    # libjpeg decodes the first half and fills the rest with grey, with a warning on stderr only
    from segs.track import run as track

    root = _copy(tmp_path)
    _truncate(root / "rgb" / "0002_rgb_raw.jpg")
    msg = _fails(tmp_path, capsys, f"data.root={root}")
    assert msg == f"error: {root / 'rgb' / '0002_rgb_raw.jpg'}: truncated JPEG (the data ends before the end-of-image marker)"
    cfg = compose(FAST + [f"data.root={root}", "task_name=track"], output_dir=str(tmp_path / "track"))
    with pytest.raises(SystemExit) as exc:
        with user_errors_exit():
            track(cfg, progress=False)
    assert exc.value.code == 2 and capsys.readouterr().err.strip() == msg
    assert not (tmp_path / "track" / "tracking.json").exists()


def test_every_real_jpeg_reads_complete():
    from segs.data.files import jpeg_is_complete

    jpegs = sorted(REPO_ROOT.glob("datasets/**/*.jpg"))
    assert jpegs and all(jpeg_is_complete(p.read_bytes()) for p in jpegs)
    data = jpegs[0].read_bytes()
    assert jpeg_is_complete(data + b"\xff\xda trailing bytes after the image are ignored")
    assert not any(jpeg_is_complete(data[:cut]) for cut in (len(data) - 1, len(data) - 2, len(data) // 2, 300, 2))


def test_euroc_pair_without_baseline(tmp_path, capsys):
    mav = tmp_path / "V1_01_copy" / "mav0"
    micro = REPO_ROOT / "datasets" / "euroc_v101_micro" / "mav0"
    shutil.copytree(micro, mav)
    shutil.copy(mav / "cam0" / "sensor.yaml", mav / "cam1" / "sensor.yaml")  # cam1 where cam0 is
    msg = _fails(tmp_path, capsys, f"data.root={mav.parent}", "data=euroc", "sensor=stereo")
    assert msg.startswith(f"error: {mav / 'cam1' / 'sensor.yaml'}: T_BS puts cam1 0.0000 m from cam0")


# Every value of the list is refused before any frame is tracked, with one line and exit 2
@pytest.mark.parametrize("override,key", [
    ("seed=-1", "seed"), ("eval.ate_align=bogus", "eval.ate_align"), ("eval.lpips_weights=/nope", "eval.lpips_weights"),
    ("ckpt_path=/nope.ckpt", "ckpt_path"), ("ckpt_path=/", "ckpt_path"), ("raster.near=-1", "raster.near"),
    ("raster.far=0.001", "raster.far"), ("mapping.view_budget=0", "mapping.view_budget"),
    ("trainer.precision=16", "trainer.precision"), ("model.voxel_size=inf", "model.voxel_size"),
    ("data.downscale=1000", "data.downscale"), ("raster.backend=cuda", "raster.backend"),
    ("+eval.anything=1", "eval.anything: unknown key"), ("eval.write_ply=maybe", "eval.write_ply"),
    ("eval.ply_fit_steps=-1", "eval.ply_fit_steps")])  # fmt: skip
def test_bad_values_are_refused_before_any_work(tmp_path, capsys, monkeypatch, override, key):
    from segs.pipeline.loop import FrameLoop

    if override == "raster.backend=cuda" and torch.cuda.is_available():
        override = "raster.backend=cuda trainer.accelerator=cpu"
    monkeypatch.setattr(FrameLoop, "step", lambda self: pytest.fail("a frame was tracked before the check"))
    msg = _fails(tmp_path, capsys, *override.split())
    assert msg.startswith(("error: config key " + key, "error: " + key)), msg


def test_half_the_depth_images_missing_is_counted_in_the_results(tmp_path, caplog):
    root = _copy(tmp_path, n=16)
    lines = (root / "depth.txt").read_text().splitlines()
    (root / "depth.txt").write_text("\n".join(lines[: len(lines) - 8]) + "\n")  # the last 8 depth lines gone
    m = run(compose(FAST + [f"data.root={root}", "eval.holdout_every=4"], output_dir=str(tmp_path / "run")))
    assert m["frames"] == 8 and m["frames_dropped"] == 8 and "8 frames listed by the dataset were left out" in m["frames_note"]
    assert json.loads((tmp_path / "run" / "metrics.json").read_text())["frames_dropped"] == 8
    assert any("8 of the frames listed" in r.getMessage() for r in caplog.records)
