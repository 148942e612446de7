"""``cuda`` backend: gsplat's fused CUDA rasterizer (optional extra ``gpu``), imported lazily.

Differences from the 3D-GS semantics of the other backends, all inside gsplat: alpha is clamped
to 0.999 (not 0.99) and recent gsplat versions bound each Gaussian by 3.33 sigma per axis,
tightened by its opacity (not a 3-sigma square). Images agree closely, not bit for bit.
"""
from __future__ import annotations

import functools

import torch


@functools.lru_cache(maxsize=1)
def unavailable_reason() -> str | None:
    """None if this backend can run, else why not (checked once per process)."""
    if not torch.cuda.is_available():
        return "no CUDA device (torch.cuda.is_available() is False)"
    try:
        import gsplat  # noqa: F401
    except Exception as exc:  # ImportError, or a broken CUDA build of gsplat
        return f"gsplat is not importable ({exc}); install the extra: pip install 'segs[gpu]'"
    return None


def _grad_proxy(means2d_b: torch.Tensor) -> torch.Tensor:
    """An [N,2] tensor whose ``.grad`` mirrors gsplat's batched ``meta['means2d']`` gradient."""
    proxy = means2d_b[0].detach().clone()
    if not means2d_b.requires_grad:
        return proxy
    proxy.requires_grad_(True)

    def hook(grad: torch.Tensor) -> None:
        g = grad[0].detach()
        proxy.grad = g.clone() if proxy.grad is None else proxy.grad + g

    means2d_b.register_hook(hook)
    return proxy


def rasterize(means, quats, scales, opacities, colors, viewmat, K, width, height, background,
              near, far, eps2d):
    """Render with ``gsplat.rasterization``; returns (image, depth, alpha, means2d, radii).

    depth is gsplat's expected depth ("RGB+ED"); means2d is an [N,2] proxy whose ``.grad`` is
    filled after backward; radii [N] int32 (the larger axis for gsplat versions with 2 radii).
    """
    from gsplat import rasterization

    dtype = means.dtype
    f32 = [t.float().contiguous() for t in (means, quats, scales, opacities, colors)]
    bgs = None if background is None else background.float()[None]
    rgbd, alphas, meta = rasterization(
        *f32, viewmats=viewmat.float()[None], Ks=K.float()[None], width=width, height=height,
        near_plane=near, far_plane=far, eps2d=eps2d, packed=False, tile_size=16,
        backgrounds=bgs, render_mode="RGB+ED", rasterize_mode="classic",
    )
    means2d_b = meta["means2d"]  # [1,N,2]
    radii = meta["radii"][0]
    if radii.dim() == 2:
        radii = radii.max(dim=-1).values
    image, depth, alpha = rgbd[0, ..., :3], rgbd[0, ..., 3], alphas[0, ..., 0]
    return (image.to(dtype), depth.to(dtype), alpha.to(dtype), _grad_proxy(means2d_b),
            radii.to(torch.int32))
