"""Fused SSIM loss on the CPU (csrc/ssim.cpp, built with the raster kernels).

kornia.metrics.ssim's definition (a separable window given by the caller, 'reflect' border, the
caller's stabilisers c1 / c2, eps 1e-12 in the denominator), reduced to its mean, with a hand-written
backward pass: one C++ pass over the image each way instead of five blurred moment maps and
their autograd graph. Gradients flow to the render only (the target is ground truth).
"""
from __future__ import annotations

import torch
from torch.autograd.function import once_differentiable

from ._build import BuildError, load_extension

EPS = 1e-12  # kornia's denominator term


class _SsimCpu(torch.autograd.Function):
    """(render [C,H,W], target [C,H,W], window [taps], c1, c2) -> mean SSIM (0-d)."""

    @staticmethod
    def forward(ctx, render, target, window, c1, c2):
        ext = load_extension()
        c, h, w = render.shape
        saved = render.new_empty(3, c, h, w)
        ctx.args = (c, h, w, window.numel(), float(c1), float(c2), EPS)
        mean = ext.ssim_forward(render.data_ptr(), target.data_ptr(), window.data_ptr(), *ctx.args, saved.data_ptr(),
                                torch.get_num_threads())  # fmt: skip
        ctx.save_for_backward(render, target, window, saved)
        return render.new_tensor(mean)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):
        ext = load_extension()
        render, target, window, saved = ctx.saved_tensors
        out = torch.empty_like(render)
        ext.ssim_backward(render.data_ptr(), target.data_ptr(), window.data_ptr(), *ctx.args, saved.data_ptr(),
                          float(grad), out.data_ptr(), torch.get_num_threads())  # fmt: skip
        return out, None, None, None, None


def fused_ssim_available(render: torch.Tensor, window: int) -> bool:
    """True when the fused kernel applies to a [C,H,W] image: CPU, float32, H and W > window // 2, kernels built."""
    if render.device.type != "cpu" or render.dtype != torch.float32 or min(render.shape[-2:]) <= window // 2:
        return False
    try:
        load_extension()
    except BuildError:
        return False
    return True


@torch.compiler.disable  # a C++ kernel called through data pointers: opaque to torch.compile (its result would be a guard)
def fused_ssim(render: torch.Tensor, target: torch.Tensor, window: torch.Tensor, c1: float, c2: float) -> torch.Tensor:
    """Mean SSIM of [C,H,W] float32 CPU images with the separable window [taps] (odd, normalised) and
    stabilisers c1, c2; differentiable in ``render``."""
    if render.shape != target.shape or render.dim() != 3:
        raise ValueError(f"fused_ssim expects two [C,H,W] images of one shape, got {tuple(render.shape)} and "
                         f"{tuple(target.shape)}")  # fmt: skip
    return _SsimCpu.apply(render.contiguous(), target.detach().contiguous(), window.to(torch.float32).contiguous(), c1, c2)
