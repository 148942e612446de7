"""FPR: frequency pyramid regularization (multi-scale high-pass FFT amplitude loss).

For scale s = 0..S-1 the render and the ground truth are resized bilinearly by 2^-s; per channel
F = fftshift(fft2(image)) (unnormalized); a square ideal high-pass mask M zeroes a centred square
of half-size r = int(ratio * min(H, W) / 2) (ratio 0.4); the scale's loss is the mean over all
C*H*W entries of | |M F(render)| - |M F(gt)| |; scales are weighted 2^-s.
Ablation variants: S = 1 ("sfr": the original scale only), "low" (a centred low-pass square of
half-size int(0.1 * min(H, W)), amplitude + phase terms as in FreGS) and "low_high" (both).
"""
from __future__ import annotations

import functools

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
    """Mean over C*H*W of | |M Fr| - |M Fg| | on full centred spectra (the definition; tests)."""
    return ((mask * fr).abs() - (mask * fg).abs()).abs().mean()


def phase_loss(fr: torch.Tensor, fg: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean over the masked entries of |angle(Fr) - angle(Fg)| (FreGS's phase term)."""
    diff = (torch.angle(fr) - torch.angle(fg)).abs()
    return (mask * diff).sum() / (mask.sum() * fr.shape[0]).clamp_min(1.0)


def reference_frequency_loss(render: torch.Tensor, gt: torch.Tensor, mode: str = "high", hp_ratio: float = 0.4,
                             lp_ratio: float = 0.1) -> torch.Tensor:  # fmt: skip
    """L_hf of one scale for [C,H,W] images, written on the full centred spectrum (slow; the oracle)."""
    h, w = render.shape[-2:]
    fr, fg = spectrum(render), spectrum(gt)
    loss = render.new_zeros(())
    if mode in ("high", "low_high"):
        loss = loss + amplitude_loss(fr, fg, highpass_mask(h, w, hp_ratio, render.device))
    if mode in ("low", "low_high"):
        m = lowpass_mask(h, w, lp_ratio, render.device)
        loss = loss + amplitude_loss(fr, fg, m) + phase_loss(fr, fg, m)
    return loss


@functools.lru_cache(maxsize=32)
def half_weights(mask_kind: str, h: int, w: int, ratio: float, device: str) -> torch.Tensor:
    """[H, W//2+1] weights of rfft2 entries: how many full-spectrum entries of the mask each stands for.

    A real image's spectrum is conjugate-symmetric, F(-k) = conj F(k), so |F| and |angle F| agree at
    k and -k; entry (ky, kx) of the half spectrum stands for itself and its mirror, except the
    columns kx = 0 and kx = W/2 (W even) whose mirrors are in the half spectrum already.
    """
    make = highpass_mask if mask_kind == "high" else lowpass_mask
    m = torch.fft.ifftshift(make(h, w, ratio), dim=(0, 1))  # mask in unshifted frequency order
    half = w // 2 + 1
    mirror = m[(-torch.arange(h)) % h][:, (-torch.arange(half)) % w]
    weights = m[:, :half] + mirror
    weights[:, 0] = m[:, 0]
    if w % 2 == 0:
        weights[:, w // 2] = m[:, w // 2]
    return weights.to(device)


def frequency_loss(render: torch.Tensor, gt: torch.Tensor, mode: str = "high", hp_ratio: float = 0.4,
                   lp_ratio: float = 0.1) -> torch.Tensor:  # fmt: skip
    """L_hf of one scale for [C,H,W] images: reference_frequency_loss on the half spectrum (rfft2).

    Equal to the full-spectrum definition up to float rounding, at about half the cost and without
    the fftshift copies.
    """
    h, w = render.shape[-2:]
    return weighted_frequency_loss(render, gt, scale_weights(h, w, mode, hp_ratio, lp_ratio, str(render.device)))


@functools.lru_cache(maxsize=32)
def scale_weights(h: int, w: int, mode: str, hp_ratio: float, lp_ratio: float, device: str) -> tuple[torch.Tensor | None, ...]:
    """(high-pass, low-pass) half-spectrum weights [H, W//2+1] of one scale, None where `mode` has no such term."""
    if mode not in MODES:
        raise ValueError(f"model.fpr.mode must be one of {MODES}, got {mode!r}")
    high = half_weights("high", h, w, hp_ratio, device) if mode in ("high", "low_high") else None
    low = half_weights("low", h, w, lp_ratio, device) if mode in ("low", "low_high") else None
    return high, low


def weighted_frequency_loss(render: torch.Tensor, gt: torch.Tensor, weights: tuple[torch.Tensor | None, ...]) -> torch.Tensor:
    """frequency_loss of [C,H,W] images with its (high, low) weights given (scale_weights)."""
    high, low = weights
    c, h, w = render.shape[-3:]
    fr = torch.fft.rfft2(render, dim=(-2, -1))
    with torch.no_grad():
        fg = torch.fft.rfft2(gt, dim=(-2, -1))
    loss = render.new_zeros(())
    if high is not None:
        loss = loss + (high * (fr.abs() - fg.abs()).abs()).sum() / (c * h * w)
    if low is not None:
        loss = loss + (low * (fr.abs() - fg.abs()).abs()).sum() / (c * h * w)
        phase = (torch.angle(fr) - torch.angle(fg)).abs()
        loss = loss + (low * phase).sum() / (low.sum() * c).clamp_min(1.0)
    return loss


@functools.lru_cache(maxsize=32)
def pyramid_weights(h: int, w: int, scales: int, mode: str, hp_ratio: float, lp_ratio: float, device: str) -> tuple:
    """scale_weights of each level s = 0..scales-1 of an H x W image (level s: max(H >> s, 1) x max(W >> s, 1))."""
    return tuple(scale_weights(max(h >> s, 1), max(w >> s, 1), mode, hp_ratio, lp_ratio, device) for s in range(scales))


def pyramid_loss(render: torch.Tensor, gt: torch.Tensor, weights: tuple) -> torch.Tensor:
    """sum_s 2^-s L_hf(down_s(render), down_s(gt)) for [H,W,C] images with the levels' weights
    (pyramid_weights): a pure function of tensors. Eager on every device: its torch.compile form
    was slower on an H200 (bench/fpr.py: 1.84 against 1.42 ms per forward + backward at 640x480)."""
    r0 = render.permute(2, 0, 1).unsqueeze(0)
    g0 = gt.permute(2, 0, 1).unsqueeze(0)
    h, w = r0.shape[-2:]
    total = render.new_zeros(())
    for s, level in enumerate(weights):
        r, g = r0, g0
        if s > 0:  # bilinear resize of the full-resolution images by 2^-s
            size = (max(h >> s, 1), max(w >> s, 1))
            r = F.interpolate(r0, size=size, mode="bilinear", align_corners=False)
            g = F.interpolate(g0, size=size, mode="bilinear", align_corners=False)
        total = total + 2.0**-s * weighted_frequency_loss(r[0], g[0], level)
    return total


def fpr_loss(render: torch.Tensor, gt: torch.Tensor, scales: int = 3, mode: str = "high", hp_ratio: float = 0.4,
             lp_ratio: float = 0.1) -> torch.Tensor:  # fmt: skip
    """sum_s 2^-s L_hf(down_s(render), down_s(gt)) for [H,W,C] images, s = 0..scales-1."""
    h, w = render.shape[:2]
    return pyramid_loss(render, gt, pyramid_weights(h, w, scales, mode, hp_ratio, lp_ratio, str(render.device)))
