"""Fused SSIM loss on the CPU (csrc/ssim.cpp, built with the raster kernels).

kornia.metrics.ssim's definition (separable Gaussian window, 'reflect' border, C1 = (0.01 L)^2,
C2 = (0.03 L)^2, eps 1e-12 in the denominator), reduced to its mean, with a hand-written
backward pass: one C++ pass over the image each way instead of five blurred moment maps and
their autograd graph. Gradients flow to the render only (the target is ground truth).
"""
from __future__ import annotations

import torch
from torch.autograd.function import once_differentiable

from ._build import BuildError, load_extension

C1, C2, EPS = 0.01**2, 0.03**2, 1e-12


def gaussian_window(taps: int, sigma: float = 1.5) -> torch.Tensor:
    """[taps] float32 normalised Gaussian, centred (kornia's get_gaussian_kernel1d)."""
    x = torch.arange(taps, dtype=torch.float64) - (taps - 1) / 2
    w = torch.exp(-(x**2) / (2 * sigma**2))
    return (w / w.sum()).to(torch.float32)


class _SsimCpu(torch.autograd.Function):
    """(render [C,H,W], target [C,H,W], window [taps]) -> mean SSIM (0-d)."""

    @staticmethod
    def forward(ctx, render, target, window):
        ext = load_extension()
        c, h, w = render.shape
        saved = render.new_empty(3, c, h, w)
        args = (render.data_ptr(), target.data_ptr(), window.data_ptr(), c, h, w, window.numel(), C1, C2, EPS)
        mean = ext.ssim_forward(*args, saved.data_ptr(), torch.get_num_threads())
        ctx.save_for_backward(render, target, window, saved)
        ctx.args = (c, h, w, window.numel(), C1, C2, EPS)
        return render.new_tensor(mean)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):
        ext = load_extension()
        render, target, window, saved = ctx.saved_tensors
        out = torch.empty_like(render)
        ext.ssim_backward(render.data_ptr(), target.data_ptr(), window.data_ptr(), *ctx.args, saved.data_ptr(),
                          float(grad), out.data_ptr(), torch.get_num_threads())  # fmt: skip
        return out, None, None


def fused_ssim_available(render: torch.Tensor, window: int) -> bool:
    """True when the fused kernel applies to a [C,H,W] image: CPU, float32, H and W > window // 2, kernels built."""
    if render.device.type != "cpu" or render.dtype != torch.float32 or min(render.shape[-2:]) <= window // 2:
        return False
    try:
        load_extension()
    except BuildError:
        return False
    return True


def fused_ssim(render: torch.Tensor, target: torch.Tensor, window: int = 11) -> torch.Tensor:
    """Mean SSIM of [C,H,W] float32 CPU images; differentiable in ``render``."""
    if render.shape != target.shape or render.dim() != 3:
        raise ValueError(f"fused_ssim expects two [C,H,W] images of one shape, got {tuple(render.shape)} and "
                         f"{tuple(target.shape)}")  # fmt: skip
    return _SsimCpu.apply(render.contiguous(), target.detach().contiguous(), gaussian_window(window))
