"""FPR: frequency pyramid regularization (multi-scale high-pass FFT amplitude loss).

For scale s = 0..S-1 the render and the ground truth are resized bilinearly by 2^-s; per channel
F = fftshift(fft2(image)) (unnormalized); a square ideal high-pass mask M zeroes a centred square
of half-size r = int(ratio * min(H, W) / 2) (ratio 0.4); the scale's loss is the mean over all
C*H*W entries of | |M F(render)| - |M F(gt)| |; scales are weighted 2^-s.
Ablation variants: S = 1 ("sfr": the original scale only), "low" (a centred low-pass square of
half-size int(0.1 * min(H, W)), amplitude + phase terms as in FreGS) and "low_high" (both).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

MODES = ("high", "low", "low_high")


def highpass_mask(h: int, w: int, ratio: float = 0.4, device=None) -> torch.Tensor:
    """[H,W] float mask: 1 everywhere except a centred square of half-size int(ratio*min(H,W)/2)."""
    r = int(ratio * min(h, w) / 2)
    m = torch.ones(h, w, device=device)
    cy, cx = h // 2, w // 2
    m[max(cy - r, 0) : cy + r, max(cx - r, 0) : cx + r] = 0.0
    return m


def lowpass_mask(h: int, w: int, ratio: float = 0.1, device=None) -> torch.Tensor:
    """[H,W] float mask: 1 inside a centred square of half-size int(ratio*min(H,W)), else 0."""
    r = int(ratio * min(h, w))
    m = torch.zeros(h, w, device=device)
    cy, cx = h // 2, w // 2
    m[max(cy - r, 0) : cy + r, max(cx - r, 0) : cx + r] = 1.0
    return m


def spectrum(image: torch.Tensor) -> torch.Tensor:
    """[C,H,W] real -> centred complex spectrum [C,H,W] (unnormalized FFT)."""
    return torch.fft.fftshift(torch.fft.fft2(image, dim=(-2, -1)), dim=(-2, -1))


def amplitude_loss(fr: torch.Tensor, fg: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean over C*H*W of | |M Fr| - |M Fg| |."""
    return ((mask * fr).abs() - (mask * fg).abs()).abs().mean()


def phase_loss(fr: torch.Tensor, fg: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean over the masked entries of |angle(Fr) - angle(Fg)| (FreGS's phase term)."""
    diff = (torch.angle(fr) - torch.angle(fg)).abs()
    return (mask * diff).sum() / (mask.sum() * fr.shape[0]).clamp_min(1.0)


def frequency_loss(render: torch.Tensor, gt: torch.Tensor, mode: str = "high", hp_ratio: float = 0.4,
                   lp_ratio: float = 0.1) -> torch.Tensor:  # fmt: skip
    """L_hf of one scale for [C,H,W] images."""
    h, w = render.shape[-2:]
    fr, fg = spectrum(render), spectrum(gt)
    loss = render.new_zeros(())
    if mode in ("high", "low_high"):
        loss = loss + amplitude_loss(fr, fg, highpass_mask(h, w, hp_ratio, render.device))
    if mode in ("low", "low_high"):
        m = lowpass_mask(h, w, lp_ratio, render.device)
        loss = loss + amplitude_loss(fr, fg, m) + phase_loss(fr, fg, m)
    return loss


def fpr_loss(render: torch.Tensor, gt: torch.Tensor, scales: int = 3, mode: str = "high", hp_ratio: float = 0.4,
             lp_ratio: float = 0.1) -> torch.Tensor:  # fmt: skip
    """sum_s 2^-s L_hf(down_s(render), down_s(gt)) for [H,W,C] images, s = 0..scales-1."""
    if mode not in MODES:
        raise ValueError(f"model.fpr.mode must be one of {MODES}, got {mode!r}")
    r0 = render.permute(2, 0, 1).unsqueeze(0)
    g0 = gt.permute(2, 0, 1).unsqueeze(0)
    h, w = r0.shape[-2:]
    total = render.new_zeros(())
    for s in range(scales):
        r, g = r0, g0
        if s > 0:  # bilinear resize of the full-resolution images by 2^-s
            size = (max(h >> s, 1), max(w >> s, 1))
            r = F.interpolate(r0, size=size, mode="bilinear", align_corners=False)
            g = F.interpolate(g0, size=size, mode="bilinear", align_corners=False)
        total = total + 2.0**-s * frequency_loss(r[0], g[0], mode, hp_ratio, lp_ratio)
    return total
