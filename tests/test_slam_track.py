"""The tracking-only entry point `python -m segs.track` (same configs as segs.train)."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

from segs.config import compose
from segs.errors import ConfigError
from segs.track import lost_ranges, run

BASE = ["+experiment=synthetic", "data.n_frames=12", "data.width=320", "data.height=240",
        "data.trajectory=orbit", "data.speed=0.2"]


def test_track_writes_trajectory_keyframes_and_metrics(tmp_path):
    cfg = compose(BASE + ["data.blank_frames=[[8,10]]"], output_dir=str(tmp_path))
    m = run(cfg, progress=False)
    assert (tmp_path / "trajectory.txt").exists() and (tmp_path / "keyframes.txt").exists()
    saved = json.loads((tmp_path / "tracking.json").read_text())
    assert saved["frames"] == 12 and saved["sensor"] == "rgbd"
    assert saved["lost_ranges"] == [[8, 9]] and saved["frames_tracked"] == 10
    assert saved["tracked_fraction"] == pytest.approx(10 / 12)
    assert saved["ate"]["align"] == "se3" and saved["ate_rmse_m"] < 0.01
    assert saved["tracking_fps"] > 0 and saved["keyframes"] >= 1
    assert 0 < saved["wall_fps"] == pytest.approx(saved["frames"] / saved["wall_s"])
    lines = [ln for ln in (tmp_path / "trajectory.txt").read_text().splitlines() if ln.strip()]
    assert len(lines) == 10 and len(lines[0].split()) == 8
    assert m["ate_rmse_m"] == saved["ate_rmse_m"]


def test_an_interrupted_track_keeps_the_poses_so_far_and_looks_unfinished(tmp_path, monkeypatch, capsys):
    """Ctrl-C while tracking (simulated at frame 6): trajectory_partial.txt holds frames 0-5, no
    trajectory.txt or tracking.json is written, the reader process is stopped."""
    import multiprocessing

    from segs.slam.orb import OrbFrontend

    process = OrbFrontend.process

    def interrupted_at_6(self, frame):
        if frame.index == 6:
            raise KeyboardInterrupt
        return process(self, frame)

    monkeypatch.setattr(OrbFrontend, "process", interrupted_at_6)
    with pytest.raises(KeyboardInterrupt):
        run(compose(BASE, output_dir=str(tmp_path)), progress=False)
    lines = [ln for ln in (tmp_path / "trajectory_partial.txt").read_text().splitlines() if ln.strip()]
    assert len(lines) == 6
    assert not (tmp_path / "trajectory.txt").exists() and not (tmp_path / "tracking.json").exists()
    assert "interrupted; 6 of 12 frames tracked" in capsys.readouterr().err
    assert not [p for p in multiprocessing.active_children() if p.name == "segs-frames"]


def test_write_trajectory_writes_the_tracked_frames_or_an_empty_file(tmp_path):
    import numpy as np

    from segs.trajectory import write_trajectory

    w2c = np.eye(4)
    w2c[:3, 3] = [1.0, 2.0, 3.0]
    assert write_trajectory(tmp_path / "t.txt", np.array([0.0, 0.5, 1.0]), {2: w2c, 0: np.eye(4)}) == 2
    rows = [ln.split() for ln in (tmp_path / "t.txt").read_text().splitlines() if ln.strip()]
    assert [float(r[0]) for r in rows] == [0.0, 1.0] and [float(v) for v in rows[1][1:4]] == [-1.0, -2.0, -3.0]
    assert write_trajectory(tmp_path / "e.txt", np.array([0.0]), {}) == 0
    assert (tmp_path / "e.txt").read_text() == ""


def test_track_rejects_unknown_slam_keys_as_user_error(tmp_path):
    cfg = compose(BASE + ["+slam.tracking.no_such_key=1"], output_dir=str(tmp_path))
    with pytest.raises(ConfigError, match="no_such_key"):
        run(cfg, progress=False)
    out = subprocess.run([sys.executable, "-m", "segs.track", *BASE, "+slam.tracking.no_such_key=1",
                          f"hydra.run.dir={tmp_path / 'cli'}"], capture_output=True, text=True)
    assert out.returncode == 2
    assert out.stderr.strip().splitlines()[-1].startswith("error: slam.tracking.no_such_key: unknown key")
    assert "Traceback" not in out.stderr



def test_track_does_not_import_torch(tmp_path):
    """Tracking builds no mapper: segs.track runs without importing torch (2-3 s, about 200 MB)."""
    code = ("import sys; from segs.config import compose; from segs.track import run; "
            f"run(compose({BASE!r}, output_dir={str(tmp_path)!r}), progress=False); "
            "print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == "False"

def test_lost_ranges():
    assert lost_ranges([]) == []
    assert lost_ranges([3, 4, 5, 9]) == [[3, 5], [9, 9]]
