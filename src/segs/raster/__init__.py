"""segs.raster: differentiable 3D Gaussian rasterizer (3D-GS semantics, gsplat-style API).

>>> render = rasterize(means, quats, scales, opacities, colors, viewmat, K, width, height)
>>> loss = (render.image - target).abs().mean(); loss.backward()
>>> render.means2d.grad  # [N,2] screen-space gradient (anchor growing / densification)

Backends, one call: ``"cuda"`` (gsplat, CUDA tensors), ``"cpu"`` (C++ with OpenMP + SIMD, built
on first use and cached), ``"torch"`` (pure PyTorch, the reference), ``"auto"`` (cuda for CUDA
tensors, else cpu, falling back to torch with a one-time warning). The same C++ build also
carries ``fused_ssim``, the SSIM loss with its backward pass in one kernel (CPU, float32). This
package imports nothing else of segs.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from . import _cpu_backend, _cuda_backend, _torch_backend
from ._backends import BackendUnavailableError, available_backends, resolve
from ._build import BuildError
from ._checks import check_inputs
from ._projection import EPS2D
from ._ssim import fused_ssim, fused_ssim_available

__all__ = ["Render", "rasterize", "EPS2D", "available_backends", "BackendUnavailableError", "BuildError", "fused_ssim",
           "fused_ssim_available"]


@dataclass
class Render:
    """Output of :func:`rasterize` (H = height, W = width, N = number of Gaussians).

    image [H,W,3]: sum_i w_i c_i + T_final * background, w_i = alpha_i T_i (front to back).
    depth [H,W]: expected camera z, sum_i w_i z_i / alpha (0 where alpha = 0); depth * alpha is
        the accumulated depth sum_i w_i z_i.
    alpha [H,W]: 1 - T_final, the accumulated opacity.
    means2d [N,2]: projected means in pixels (pixel centres at +0.5); after backward its
        ``.grad`` holds d loss / d means2d.
    radii [N] int32: screen radius in pixels, 0 = not drawn (culled).
    backend: the backend that rendered ("cuda", "cpu" or "torch").
    """

    image: torch.Tensor
    depth: torch.Tensor
    alpha: torch.Tensor
    means2d: torch.Tensor
    radii: torch.Tensor
    backend: str


def rasterize(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    viewmat: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    background: torch.Tensor | None = None,
    near: float = 0.01,
    far: float = 100.0,
    backend: str = "auto",
    check_values: bool = True,
    eps2d: float = EPS2D,
) -> Render:
    """Render N Gaussians into a ``width`` x ``height`` image, differentiably.

    Args:
        means [N,3] world positions; quats [N,4] rotations, wxyz, any norm (normalised here);
        scales [N,3] standard deviations along the rotated axes (already activated);
        opacities [N] in [0,1]; colors [N,3]; viewmat [4,4] world-to-camera; K [3,3] pinhole
        intrinsics; background [3] colour behind the Gaussians (default black);
        near, far: Gaussians with camera z outside [near, far] are culled;
        backend: "auto", "cuda", "cpu" or "torch";
        check_values: also read the values back (finite entries, positive focal lengths): on a
            GPU that read waits for the device, so a training loop may check only some steps;
        eps2d: the low-pass filter, pixels^2 added to the diagonal of every 2D covariance (3D-GS's
            0.3; larger values render the Gaussians as if seen through coarser pixels).

    All tensors must share one float dtype (float32 or float64) and one device, with finite
    values; otherwise ValueError names the argument, its shape and the expected one.
    Gradients reach means, quats, scales, opacities, colors and background from image, depth
    and alpha; viewmat too when it requires grad (the cpu backend then projects in PyTorch).
    Semantics (3D-GS): EWA projection with an eps2d px^2 low-pass,
    3-sigma extent, 16x16 tiles, front-to-back order by camera z, alpha = min(0.99, o exp(-s)),
    contributions below 1/255 skipped, a pixel stops before its transmittance drops below 1e-4.
    """
    check_inputs(means, quats, scales, opacities, colors, viewmat, K, width, height,
                 background, near, far, check_values, eps2d)
    name = resolve(backend, means.device)
    if name == "cuda":
        out = _cuda_backend.rasterize(means, quats, scales, opacities, colors, viewmat, K,
                                      width, height, background, near, far, eps2d)
        return Render(*out, backend="cuda")
    impl = _cpu_backend if name == "cpu" else _torch_backend
    proj = impl.project(means, quats, scales, viewmat, K, width, height, near, far, eps2d)
    means2d = proj.means2d
    if means2d.requires_grad:
        means2d.retain_grad()
    if background is None:
        background = torch.zeros(3, dtype=means.dtype, device=means.device)
    image, depth, alpha = impl.rasterize_pixels(
        means2d, proj.conics, colors, opacities, proj.depths, proj.radii, width, height, background
    )
    return Render(image, depth, alpha, means2d, proj.radii, backend=name)
