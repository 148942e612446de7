"""Photometric loss terms: L1, D-SSIM (kornia) and the Scaffold-GS volume regularizer."""
from __future__ import annotations

import kornia
import torch


def to_bchw(image: torch.Tensor) -> torch.Tensor:
    """[H,W,C] -> [1,C,H,W]."""
    return image.permute(2, 0, 1).unsqueeze(0)


def l1(render: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Mean absolute error of [H,W,3] images."""
    return (render - gt).abs().mean()


def ssim(render: torch.Tensor, gt: torch.Tensor, window: int = 11) -> torch.Tensor:
    """Mean SSIM of [H,W,3] images (Gaussian window, sigma 1.5, C1 = 0.01^2, C2 = 0.03^2)."""
    return kornia.metrics.ssim(to_bchw(render), to_bchw(gt), window_size=window, max_val=1.0).mean()


def volume(scales: torch.Tensor) -> torch.Tensor:
    """L_vol: mean over Gaussians of the product of their 3 scales; scales [N,3]."""
    if scales.shape[0] == 0:
        return scales.sum()
    return scales.prod(dim=1).mean()


def photometric(render: torch.Tensor, gt: torch.Tensor, lambda_dssim: float) -> dict[str, torch.Tensor]:
    """(1 - lambda) L1 + lambda (1 - SSIM) on [H,W,3] images; returns the terms and their sum."""
    l_1 = l1(render, gt)
    s = ssim(render, gt)
    return {"l1": l_1, "ssim": s, "photometric": (1.0 - lambda_dssim) * l_1 + lambda_dssim * (1.0 - s)}


def depth_l1(depth: torch.Tensor, gt_depth: torch.Tensor) -> torch.Tensor:
    """Mean |depth - gt| over pixels with valid ground truth (> 0); [H,W] each."""
    valid = gt_depth > 0
    if not bool(valid.any()):
        return depth.sum() * 0.0
    return (depth[valid] - gt_depth[valid]).abs().mean()
