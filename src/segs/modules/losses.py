"""Photometric loss terms: L1, D-SSIM (fused C++ kernel on the CPU, kornia elsewhere) and the Scaffold-GS volume regularizer.

kornia is imported only where its blur runs (not on the CPU): importing it costs about 19 MB of
resident memory, a fifth of issue 40's margin (docs/decisions/029-peak-memory.md)."""
from __future__ import annotations

import torch

from segs.raster import fused_ssim, fused_ssim_available

_C1, _C2 = 0.01**2, 0.03**2  # SSIM stabilisers for images in [0, 1]


def to_bchw(image: torch.Tensor) -> torch.Tensor:
    """[H,W,C] -> [1,C,H,W]."""
    return image.permute(2, 0, 1).unsqueeze(0)


def l1(render: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Mean absolute error of [H,W,3] images."""
    return (render - gt).abs().mean()


def ssim(render: torch.Tensor, gt: torch.Tensor, window: int = 11) -> torch.Tensor:
    """Mean SSIM of [H,W,3] images (Gaussian window, sigma 1.5, C1 = 0.01^2, C2 = 0.03^2, reflect border).

    kornia.metrics.ssim's map, with its five blurs stacked into two filter calls: the ground truth's
    moments (mu_g, E[g^2]) without autograd, the render's (mu_r, E[r^2], E[rg]) in one call. Same
    value and gradient to float rounding, about 1.5x faster forward + backward at 640x480. On the
    CPU in float32 the fused C++ kernel of segs.raster computes the same in one pass each way
    (about 6x faster than kornia at 640x480).
    """
    kernel = gaussian_window(window, 1.5, render)
    if fused_ssim_available(render.permute(2, 0, 1), window):
        return fused_ssim(render.permute(2, 0, 1), gt.permute(2, 0, 1), kernel, _C1, _C2)
    import kornia

    kernel = kernel[None]  # [1, taps]
    r, g = to_bchw(render), to_bchw(gt)
    c = r.shape[1]
    blur = lambda x: kornia.filters.filter2d_separable(x, kernel, kernel, border_type="reflect")  # noqa: E731
    with torch.no_grad():
        mg = blur(torch.cat([g, g * g], dim=1))
    mr = blur(torch.cat([r, r * r, r * g], dim=1))
    mu_r, mu_g = mr[:, :c], mg[:, :c]
    mu_rr, mu_gg, mu_rg = mu_r * mu_r, mu_g * mu_g, mu_r * mu_g
    var_r, var_g, cov = mr[:, c : 2 * c] - mu_rr, mg[:, c:] - mu_gg, mr[:, 2 * c :] - mu_rg
    num = (2.0 * mu_rg + _C1) * (2.0 * cov + _C2)
    den = (mu_rr + mu_gg + _C1) * (var_r + var_g + _C2)
    return (num / (den + 1e-12)).mean()


def gaussian_window(taps: int, sigma: float, like: torch.Tensor) -> torch.Tensor:
    """[taps] normalised Gaussian weights centred on the middle tap (odd taps), on the device and in
    the dtype of ``like``: kornia.filters.get_gaussian_kernel1d's arithmetic, so the same bits (the
    training loss is unchanged; torch.signal.windows.gaussian differs in the last bit)."""
    x = torch.arange(taps, dtype=like.dtype, device=like.device) - taps // 2
    w = torch.exp(-(x**2) / (2 * sigma**2))
    return w / w.sum()


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
    """Mean |depth - gt| over pixels with valid ground truth (> 0), 0 where none is; [H,W] each.
    Masked sums, not depth[valid]: no data-dependent shape, so no device-to-host sync on a GPU."""
    valid = gt_depth > 0
    err = torch.where(valid, (depth - gt_depth).abs(), torch.zeros_like(depth))
    return err.sum() / valid.sum().clamp_min(1)
