"""bench/ate_diagnostics.py: the lever-arm and time-offset tests recover what was put in (synthetic
trajectories in a 7-Scenes-style folder; the real frames are not needed)."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from conftest import load_bench

ROOT = Path(__file__).resolve().parents[1]


def _bench():
    return load_bench("ate_diagnostics")


def _depth_track(n: int, rng: np.random.Generator) -> np.ndarray:
    """[n,4,4] camera-to-world poses of a camera that pans and tilts by tens of degrees while it moves."""
    t = np.linspace(0, 1, n)
    rot = Rotation.from_euler("xyz", np.stack([0.5 * np.sin(3 * t), 0.8 * np.sin(2 * t + 1), 0.2 * t], 1)).as_matrix()
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = rot
    T[:, :3, 3] = np.stack([np.sin(t), 0.3 * t, np.cos(2 * t)], 1) + 0.001 * rng.standard_normal((n, 3))
    return T


def _write(folder: Path, T_depth: np.ndarray, est: np.ndarray) -> Path:
    """A 7-Scenes folder (poses + empty colour files) and a TUM trajectory of centres est [N,3]."""
    folder.mkdir()
    for i, T in enumerate(T_depth):
        np.savetxt(folder / f"frame-{i:06d}.pose.txt", T)
        (folder / f"frame-{i:06d}.color.png").write_bytes(b"")
    lines = np.column_stack([np.arange(len(est)) / 30.0, est, np.zeros((len(est), 3)), np.ones(len(est))])
    path = folder.parent / "trajectory.txt"
    np.savetxt(path, lines)
    return path


def test_lever_arm_and_alignment_recovered(tmp_path):
    bench = _bench()
    rng = np.random.default_rng(0)
    T = _depth_track(120, rng)
    lever = np.array([0.05, -0.02, 0.01])
    A = Rotation.from_rotvec([0.3, -0.2, 1.0]).as_matrix()
    est = (bench.colour_centres(T, lever) - 0.5) @ A  # the colour centres in another world frame
    res = bench.diagnose(_write(tmp_path / "seq", T, est), tmp_path / "seq", [0.0])
    assert res["ate_cm_fitted_lever"] < 0.01
    assert np.allclose(res["fitted_lever_cm"], 100 * lever, atol=0.05)
    assert res["ate_cm_no_lever"] > 0.5  # a 5 cm lever arm under tens of degrees of rotation shows


def test_time_offset_found(tmp_path):
    bench = _bench()
    T = _depth_track(200, np.random.default_rng(1))
    C = bench.colour_centres(T, bench.reader_lever())
    est = 0.5 * (C[1:] + C[:-1])  # frame i estimated where the ground truth is at i + 0.5
    res = bench.diagnose(_write(tmp_path / "seq", T, est), tmp_path / "seq", [-0.5, 0.0, 0.5])
    by = {o["frames"]: o["ate_cm"] for o in res["time_offsets"]}
    assert by[0.5] == pytest.approx(0.0, abs=1e-6)
    assert by[0.0] > by[0.5] and by[-0.5] > by[0.0]
    assert res["ate_cm_reader"] == pytest.approx(by[0.0])


def test_epipolar_test_prefers_the_true_relative_pose():
    """Consistent SIFT matches of two synthetic frames (exact poses) sit on the true pose's epipolar
    lines (sub-pixel Sampson distance) and off those of a pose rotated by half a degree."""
    from segs.data.synthetic import SyntheticSequence
    from segs.slam.geometry import fundamental, inv_se3, sampson_distance

    bench = _bench()
    seq = SyntheticSequence(sensor="rgbd", n_frames=60, width=320, height=240)
    grey = [cv2.cvtColor((seq[i].rgb * 255).round().astype(np.uint8), cv2.COLOR_RGB2GRAY) for i in (0, 2)]
    m = bench.consistent_matches(grey[0], grey[1], cv2.SIFT_create())
    assert m is not None
    xi, xj, F_fit = m
    w2c0, w2c2 = inv_se3(seq.gt_poses[0]), inv_se3(seq.gt_poses[2])
    true = np.median(sampson_distance(fundamental(w2c0, w2c2, seq.camera.K), xi, xj))
    turned = w2c2.copy()
    turned[:3, :3] = Rotation.from_euler("y", 0.5, degrees=True).as_matrix() @ w2c2[:3, :3]
    off = np.median(sampson_distance(fundamental(w2c0, turned, seq.camera.K), xi, xj))
    fit = np.median(sampson_distance(F_fit, xi, xj))
    assert true < 0.5 and off > 2 * true and fit <= 1.0


def test_c2w_from_tum_row():
    bench = _bench()
    T = bench._c2w(np.array([1.0, 2.0, 3.0, 0.0, 0.0, np.sin(0.25), np.cos(0.25)]))
    assert np.allclose(T[:3, 3], [1, 2, 3]) and np.isclose(Rotation.from_matrix(T[:3, :3]).magnitude(), 0.5)
