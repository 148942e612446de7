"""Metric functions against hand-computed values; LPIPS only from a real weights file."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from torchmetrics.functional.image import structural_similarity_index_measure

from segs.data.tum import TumSequence
from segs.errors import ConfigError
from segs.modules.metrics import Lpips, alexnet_features, make_lpips, psnr, ssim
from segs.trajectory import ate, step_scale

SAMPLE = Path(__file__).resolve().parents[1] / "datasets" / "tum_fr3_cabinet_kf"


def test_psnr_is_the_mean_of_per_channel_psnr():
    gt = torch.zeros(4, 4, 3)
    render = gt.clone()
    render[..., 0] = 0.1  # MSE 0.01 -> 20 dB
    render[..., 1] = 0.01  # MSE 1e-4 -> 40 dB
    render[..., 2] = 0.001  # MSE 1e-6 -> 60 dB
    assert psnr(render, gt) == pytest.approx((20 + 40 + 60) / 3, rel=1e-5)


def test_ssim_identity_and_constant_images():
    img = torch.rand(32, 32, 3)
    assert ssim(img, img) == pytest.approx(1.0, abs=1e-6)
    # two constant images a, b: SSIM = (2ab + C1) / (a^2 + b^2 + C1) everywhere
    a, b, c1 = 0.2, 0.6, 0.01**2
    got = ssim(torch.full((32, 32, 3), a), torch.full((32, 32, 3), b))
    # float32: E[x^2] - E[x]^2 of a constant image is a few 1e-8, not 0 (the worst case)
    assert got == pytest.approx((2 * a * b + c1) / (a * a + b * b + c1), rel=3e-4)


def test_ssim_in_float32_agrees_with_float64_on_images():
    torch.manual_seed(0)
    a = torch.rand(60, 80, 3)
    b = (a + 0.1 * torch.randn_like(a)).clamp(0, 1)
    ref = structural_similarity_index_measure(a.permute(2, 0, 1)[None].double(), b.permute(2, 0, 1)[None].double(),
                                              gaussian_kernel=True, sigma=1.5, kernel_size=11, data_range=1.0)  # fmt: skip
    assert ssim(a, b) == pytest.approx(float(ref), abs=1e-6)


def test_ssim_of_real_frames_agrees_with_torchmetrics_in_float64():
    """The evaluation's SSIM (the fused kernel on the CPU) against torchmetrics in float64 on the
    bundled sample's frames: pairs of neighbours and a noisy copy."""
    sample_sequence = TumSequence(SAMPLE, downscale=2, freiburg=3)
    g = torch.Generator().manual_seed(0)
    for i in (0, 20, 40):
        a, b = (torch.from_numpy(np.ascontiguousarray(sample_sequence[j].rgb)) for j in (i, i + 1))
        noisy = (a + 0.05 * torch.randn(a.shape, generator=g)).clamp(0, 1)
        for x, y in ((a, b), (noisy, a)):
            ref = structural_similarity_index_measure(x.permute(2, 0, 1)[None].double(), y.permute(2, 0, 1)[None].double(),
                                                      gaussian_kernel=True, sigma=1.5, kernel_size=11, data_range=1.0)  # fmt: skip
            assert ssim(x, y) == pytest.approx(float(ref), abs=1.5e-5)


def test_lpips_is_unavailable_without_weights():
    assert make_lpips(None) is None


def test_lpips_rejects_a_missing_or_foreign_weights_file(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        make_lpips(str(tmp_path / "missing.pth"))
    torch.save({"features.0.weight": torch.zeros(3)}, tmp_path / "foreign.pth")
    with pytest.raises(ConfigError, match="not an AlexNet"):
        Lpips(tmp_path / "foreign.pth")


def test_lpips_pipeline_runs_on_a_weights_file(tmp_path):
    # random backbone weights: only the loading and the distance properties are checked here
    torch.manual_seed(0)
    sd = {f"features.{k}": v for k, v in alexnet_features().state_dict().items()}
    torch.save(sd, tmp_path / "alexnet.pth")
    lp = Lpips(tmp_path / "alexnet.pth")
    a, b = torch.rand(64, 64, 3), torch.rand(64, 64, 3)
    assert lp(a, a) == pytest.approx(0.0, abs=1e-6)
    assert lp(a, b) > 0


def _poses(n: int) -> np.ndarray:
    c2w = np.tile(np.eye(4), (n, 1, 1))
    t = np.linspace(0, 2 * math.pi, n)
    c2w[:, :3, 3] = np.stack([np.cos(t), np.sin(t), 0.1 * t], 1)
    return c2w


def test_ate_zero_for_a_rigidly_moved_copy_and_hand_computed_offset():
    gt = _poses(30)
    ts = np.arange(30) / 30.0
    T = np.eye(4)
    T[:3, :3] = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]])
    T[:3, 3] = [3, -2, 1]
    est = {i: np.linalg.inv(T @ gt[i]) for i in range(30)}
    assert ate(ts, est, gt, "se3")["rmse"] < 1e-9
    # alternate +-1 cm along z on top of the truth: the alignment cannot remove it -> RMSE 1 cm
    noisy = {}
    for i in range(30):
        c = gt[i].copy()
        c[2, 3] += 0.01 if i % 2 else -0.01
        noisy[i] = np.linalg.inv(c)
    assert ate(ts, noisy, gt, "se3")["rmse"] == pytest.approx(0.01, rel=1e-3)


def test_ate_sim3_removes_scale_and_reports_missing_ground_truth():
    gt = _poses(20)
    ts = np.arange(20) / 30.0
    scaled = {i: np.linalg.inv(np.block([[gt[i][:3, :3], 0.5 * gt[i][:3, 3:]], [np.zeros((1, 3)), np.ones((1, 1))]])) for i in range(20)}
    r = ate(ts, scaled, gt, "sim3")
    assert r["rmse"] < 1e-9 and r["scale"] == pytest.approx(2.0, rel=1e-6)
    assert ate(ts, scaled, None)["rmse"] is None


def test_ate_of_a_rotation_in_place_falls_back_to_origin_alignment():
    # every camera centre on one point: Umeyama is degenerate; the first poses are aligned instead
    n = 12
    gt = np.tile(np.eye(4), (n, 1, 1))
    for i, a in enumerate(np.linspace(0, 2 * math.pi, n)):
        gt[i, :2, :2] = [[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]
    ts = np.arange(n) / 30.0
    est = {i: np.linalg.inv(gt[i]) for i in range(n)}
    est[5] = np.linalg.inv(gt[5] @ np.block([[np.eye(3), np.array([[0.02], [0], [0]])], [np.zeros((1, 3)), np.ones((1, 1))]]))
    r = ate(ts, est, gt, "se3")
    assert r["align"] == "origin"
    assert r["rmse"] == pytest.approx(0.02 / math.sqrt(n), rel=1e-6)


def test_step_scale_is_one_without_drift_and_shows_a_scale_jump():
    """Estimated / true path length over every 5 consecutive steps after the Sim(3) alignment."""
    n = 31
    gt = np.tile(np.eye(4), (n, 1, 1))
    gt[:, 0, 3] = np.arange(n, dtype=float)  # 1 m steps along x
    gt[:, 1, 3] = 0.1 * np.sin(np.arange(n))  # not a line (a line leaves the alignment free)
    ts = np.arange(n) / 10.0
    copy = {i: np.linalg.inv(np.block([[gt[i][:3, :3], 0.3 * gt[i][:3, 3:]], [np.zeros((1, 3)), np.ones((1, 1))]]))
            for i in range(n)}  # fmt: skip
    r = step_scale(ts, copy, gt)
    assert len(r["ratios"]) == n - 5 and r["min_rel"] == pytest.approx(1.0) and r["max_rel"] == pytest.approx(1.0)
    # the first 10 steps twice as long as the rest: 6 windows at 2x the 16 that see only the rest
    c = np.cumsum(np.r_[0.0, np.where(np.arange(n - 1) < 10, 2.0, 1.0)])
    drift = {i: np.linalg.inv(np.block([[np.eye(3), np.array([[c[i]], [gt[i, 1, 3]], [0.0]])],
                                        [np.zeros((1, 3)), np.ones((1, 1))]])) for i in range(n)}  # fmt: skip
    r = step_scale(ts, drift, gt)
    assert r["max_rel"] == pytest.approx(2.0, rel=0.02) and r["min_rel"] == pytest.approx(1.0, rel=0.02)
    assert step_scale(ts, {i: copy[i] for i in range(4)}, gt)["reason"].startswith("fewer than 5 steps")
