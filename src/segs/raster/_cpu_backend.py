"""``cpu`` backend: C++ projection and tile rasterizer (csrc/) wrapped in autograd Functions.

Both have hand-written backward passes; the PyTorch projection (``_projection.py``) is their
reference and is used instead when ``viewmat`` or ``K`` need gradients (the C++ projection
gives none). Computation is float32; float64 inputs are cast (differentiably).
"""
from __future__ import annotations

import torch
from torch.autograd.function import once_differentiable

from ._build import load_extension
from ._projection import EPS2D, Projected
from ._projection import project as project_torch


LAST_STATS: dict = {}  # work counters of the latest forward (listed Gaussians, tile-Gaussian
# intersections, pixel-Gaussian evaluations); read by bench/raster.py


def _f32(t: torch.Tensor) -> torch.Tensor:
    return t.to(torch.float32).contiguous()


class _ProjectCpu(torch.autograd.Function):
    """(means, quats, scales) -> (means2d, conics, depths, radii) for a fixed camera."""

    @staticmethod
    def forward(ctx, means, quats, scales, viewmat, K, width, height, near, far, eps2d):
        ext = load_extension()
        n = means.shape[0]
        means2d, conics = means.new_empty(n, 2), means.new_empty(n, 3)
        depths = means.new_empty(n)
        radii = torch.empty(n, dtype=torch.int32)
        camera = (viewmat, K)
        ext.project_forward(
            *[t.data_ptr() for t in (means, quats, scales, *camera)], n, width, height, near, far, eps2d,
            *[t.data_ptr() for t in (means2d, conics, depths, radii)], torch.get_num_threads(),
        )
        ctx.save_for_backward(means, quats, scales, viewmat, K)
        ctx.args = (n, width, height, near, far, eps2d)
        ctx.mark_non_differentiable(radii)
        return means2d, conics, depths, radii

    @staticmethod
    @once_differentiable
    def backward(ctx, g_means2d, g_conics, g_depths, _g_radii):
        ext = load_extension()
        inputs = ctx.saved_tensors
        n = ctx.args[0]
        grads_in = [_f32(g) for g in (g_means2d, g_conics, g_depths)]
        out = [torch.empty(n, 3), torch.empty(n, 4), torch.empty(n, 3)]
        ext.project_backward(
            *[t.data_ptr() for t in inputs], *ctx.args, *[t.data_ptr() for t in grads_in],
            *[t.data_ptr() for t in out], torch.get_num_threads(),
        )
        return (*out, None, None, None, None, None, None, None)


def project(means, quats, scales, viewmat, K, width, height, near, far, eps2d: float = EPS2D) -> Projected:
    """Same contract as :func:`segs.raster._projection.project`, in C++ (float32).

    Falls back to the PyTorch projection when viewmat or K require gradients.
    """
    if viewmat.requires_grad or K.requires_grad:
        return project_torch(means, quats, scales, viewmat, K, width, height, near, far, eps2d)
    dtype = means.dtype
    m2d, conics, depths, radii = _ProjectCpu.apply(
        _f32(means), _f32(quats), _f32(scales), _f32(viewmat), _f32(K),
        width, height, float(near), float(far), float(eps2d),
    )
    return Projected(m2d.to(dtype), conics.to(dtype), depths.to(dtype), radii)


class _RasterizeCpu(torch.autograd.Function):
    """(means2d, conics, colors, opacities, depths, background) -> (image, depth, alpha)."""

    @staticmethod
    def forward(ctx, means2d, conics, colors, opacities, depths, background, radii, width, height):
        ext = load_extension()
        threads = torch.get_num_threads()
        image = means2d.new_empty(height, width, 3)
        depth = means2d.new_empty(height, width)
        alpha = means2d.new_empty(height, width)
        ptrs = [t.data_ptr() for t in (means2d, conics, colors, opacities, depths, radii, background)]
        ctx.state = ext.forward(
            *ptrs, means2d.shape[0], width, height,
            image.data_ptr(), depth.data_ptr(), alpha.data_ptr(), threads,
        )
        st = ctx.state
        LAST_STATS.update(listed=st.n_listed, intersections=st.n_intersections,
                          evaluations=st.evaluations)
        ctx.n = means2d.shape[0]
        return image, depth, alpha

    @staticmethod
    @once_differentiable
    def backward(ctx, g_image, g_depth, g_alpha):
        ext = load_extension()
        n = ctx.n
        grads_out = [_f32(g) for g in (g_image, g_depth, g_alpha)]
        g = [torch.empty(n, 2), torch.empty(n, 3), torch.empty(n, 3), torch.empty(n),
             torch.empty(n), torch.empty(3)]  # the kernel writes every entry
        ext.backward(
            ctx.state, *[t.data_ptr() for t in grads_out], *[t.data_ptr() for t in g],
            torch.get_num_threads(),
        )
        return (*g, None, None, None)


def rasterize_pixels(means2d, conics, colors, opacities, depths, radii, width, height, background):
    """Same contract as :func:`segs.raster._torch_backend.rasterize_pixels`, in C++.

    Returns (image [H,W,3], depth [H,W] expected z, alpha [H,W]) in the dtype of ``means2d``.
    """
    dtype = means2d.dtype
    out = _RasterizeCpu.apply(
        _f32(means2d), _f32(conics), _f32(colors), _f32(opacities), _f32(depths),
        _f32(background), radii.to(torch.int32).contiguous(), width, height,
    )
    return tuple(t.to(dtype) for t in out)
