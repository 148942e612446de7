"""bench/ate_decompose.py: each part of the decomposition recovers what was put into a synthetic
trajectory (the real frames are not needed)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from conftest import load_bench

ROOT = Path(__file__).resolve().parents[1]


def _bench():
    return load_bench("ate_decompose")


def _track(n: int, angles: np.ndarray | None = None) -> np.ndarray:
    """[n,4,4] camera-to-world poses that turn and move (rotation vectors `angles` [n,3] if given)."""
    t = np.linspace(0, 1, n)
    if angles is None:
        angles = np.stack([0.5 * np.sin(3 * t), 0.8 * np.sin(2 * t + 1), 0.2 * t], 1)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.from_rotvec(angles).as_matrix()
    T[:, :3, 3] = np.stack([np.sin(t), 0.3 * t, np.cos(2 * t)], 1)
    return T


def _similar(P: np.ndarray, s: float) -> np.ndarray:
    """Centres P [N,3] in another world frame and scale."""
    return s * P @ Rotation.from_rotvec([0.3, -0.2, 1.0]).as_matrix().T + np.array([1.0, -2.0, 0.5])


def test_a_similar_trajectory_has_no_error_and_one_scale():
    bench = _bench()
    gt = _track(120)[:, :3, 3]
    d, s = bench.sim3_residuals(_similar(gt, 0.4), gt)
    assert bench.rms(d) < 1e-9 and s == pytest.approx(2.5)
    assert all(w["ate_cm"] < 1e-6 and w["scale_rel"] == pytest.approx(1.0) for w in bench.windows(_similar(gt, 0.4), gt, 40, s))


def test_a_scale_drift_shows_in_the_window_scales():
    bench = _bench()
    gt = _track(120)[:, :3, 3]
    steps = np.diff(gt, axis=0) * np.where(np.arange(119) < 60, 1.0, 1.2)[:, None]  # 20 % longer from step 60
    est = np.vstack([gt[:1], gt[0] + np.cumsum(steps, 0)])
    _, s = bench.sim3_residuals(est, gt)
    w = bench.windows(est, gt, 60, s)
    assert w[0]["scale_rel"] / w[1]["scale_rel"] == pytest.approx(1.2, rel=1e-6)
    assert max(x["ate_cm"] for x in w) < 1e-6


def test_rotation_gain_recovered_per_axis():
    bench = _bench()
    phi = np.linspace(0, 1.2, 90)
    true = _track(90, np.stack([0 * phi, phi, 0 * phi], 1))  # a pan about the camera's y axis
    est = _track(90, np.stack([0 * phi, 0.85 * phi, 0 * phi], 1))
    g = bench.rotation_gain(est, true, 10)
    assert g[1] == pytest.approx(0.85, rel=1e-6)
    assert np.isnan(g[0]) and np.isnan(g[2])


def test_constant_offset_in_the_camera_frame_recovered():
    bench = _bench()
    T = _track(150)
    offset = np.array([0.02, -0.05, 0.12])
    est = _similar(T[:, :3, 3] + T[:, :3, :3] @ offset, 0.6)
    ate, fitted = bench.fitted_offset(est, T)
    assert ate < 1e-6
    assert np.allclose(fitted, offset, atol=1e-5)
    assert bench.rms(bench.sim3_residuals(est, T[:, :3, 3])[0]) > 0.01  # the offset shows without the fit
