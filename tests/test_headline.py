"""bench/headline.py: the README's headline table comes from run folders and their provenance."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from conftest import load_bench

ROOT = Path(__file__).resolve().parents[1]
headline = load_bench("headline", "headline")

PROV = {"sensor": "rgbd", "overrides": ["+experiment=x", "seed=1"], "git_commit": "0123456789abcdef" * 2 + "01234567",
        "git_dirty": True, "machine": {"cpu": "AMD EPYC", "cores": 2}}


def _run(folder: Path, name: str, result: dict) -> Path:
    folder.mkdir(parents=True)
    (folder / name).write_text(json.dumps(result))
    return folder


def test_rows_for_a_train_and_a_track_run_and_the_readme_markers(tmp_path):
    train = _run(tmp_path / "a", "metrics.json", {
        "status": "finished", "sequence": "cabinet", "frames_tracked": 58, "frames": 58, "ate_rmse_m": None,
        "ate": {"reason": "ground-truth poses"}, "psnr": 24.61, "ssim": 0.9012, "test_views": 15, "tracking_fps": None,
        "iterations": 2000, "mapping_time_s": 101.4, "model_mb": 4.09, "provenance": PROV})
    track = _run(tmp_path / "b", "tracking.json", {
        "sequence": "kitti", "frames_tracked": 51, "frames": 51, "ate_rmse_m": 0.31, "ate": {"align": "sim3"},
        "tracking_fps": 9.25, "provenance": {**PROV, "sensor": "mono", "git_dirty": False}})
    text = headline.table([train, track])
    rows = text.splitlines()[2:]
    assert "| cabinet | rgbd | 58/58 | n/a (ground-truth poses) | 24.61 dB / 0.901 (15) | - | 2000 it, 101 s | 4.1 |" in rows[0]
    assert "0123456 (dirty)" in rows[0] and "`python -m segs.train +experiment=x seed=1`" in rows[0]
    assert "| kitti | mono | 51/51 | 31.00 cm (Sim(3)) | - | 9.2 |" in rows[1] and "(dirty)" not in rows[1]
    readme = tmp_path / "README.md"
    readme.write_text(f"intro\n{headline.BEGIN}\nold table\n{headline.END}\nafter\n")
    headline.write_between_markers(readme, text)
    assert readme.read_text() == f"intro\n{headline.BEGIN}\n{text}\n{headline.END}\nafter\n"


def test_a_folder_without_a_result_or_provenance_is_refused_by_name(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(SystemExit, match="empty: neither metrics.json nor tracking.json"):
        headline.read_run(empty)
    old = _run(tmp_path / "old", "tracking.json", {"frames": 1})
    with pytest.raises(SystemExit, match="no provenance record"):
        headline.read_run(old)
    stopped = _run(tmp_path / "stopped", "metrics.json", {"status": "not_evaluated", "provenance": PROV})
    with pytest.raises(SystemExit, match="not a finished, evaluated run"):
        headline.read_run(stopped)


def test_rows_name_the_frame_range_and_write_folders_as_the_readme_does():
    prov = {**PROV, "frontend": "known_poses", "overrides": [
        "+experiment=seven_scenes_rgbd", "data.frames=[300,600]", "data.root=/home/u/shared/data/7scenes_redkitchen_0000_0599",
        "task_name=track"]}  # fmt: skip
    result = {"sequence": "7scenes_redkitchen_0000_0599/seq", "frames_tracked": 300, "frames": 300, "ate_rmse_m": 0.0211,
              "ate": {"align": "se3"}, "tracking_fps": 700.0, "provenance": prov}  # fmt: skip
    line = headline.row("track", result)
    assert line.startswith("| 7scenes_redkitchen_0000_0599, frames 300-599 | rgbd | 300/300 | 2.11 cm (SE(3)) | - | - |")
    assert "data.root=../shared/data/7scenes_redkitchen_0000_0599`" in line and "task_name" not in line
    assert headline._portable("data.root=/work/x/datasets/tum_fr3_cabinet_kf") == "data.root=datasets/tum_fr3_cabinet_kf"
