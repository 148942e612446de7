"""Random but realistic Gaussian scenes for tests and benchmarks.

Recipe (:func:`random_scene`): pinhole camera with fx = fy = 0.8 * width, principal point at
the image centre, a random (seeded) camera pose. Means are drawn uniformly in the camera frustum
2-6 m in front of the camera (x/z, y/z spanning the field of view plus 5 %), scales log-uniform
in [0.5, 5] cm per axis, random rotations, opacities uniform in [0.05, 1], colours uniform in
[0, 1]. 20k Gaussians at 320x240 give a mean alpha of 0.86; 100k at 640x480 saturate every
pixel (alpha > 0.99).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch


@dataclass
class Scene:
    """Inputs of :func:`segs.raster.rasterize` (all tensors on one device and dtype)."""

    means: torch.Tensor  # [N,3] world
    quats: torch.Tensor  # [N,4] wxyz, unit
    scales: torch.Tensor  # [N,3] metres
    opacities: torch.Tensor  # [N]
    colors: torch.Tensor  # [N,3]
    viewmat: torch.Tensor  # [4,4] world-to-camera
    K: torch.Tensor  # [3,3]
    width: int
    height: int

    def params(self) -> list[torch.Tensor]:
        """The five per-Gaussian tensors, in rasterize() order."""
        return [self.means, self.quats, self.scales, self.opacities, self.colors]

    def requires_grad_(self) -> "Scene":
        for t in self.params():
            t.requires_grad_(True)
        return self


def _rotation(axis_angle: torch.Tensor) -> torch.Tensor:
    """Rodrigues: [3] -> [3,3]."""
    theta = float(axis_angle.norm())
    if theta < 1e-12:
        return torch.eye(3, dtype=axis_angle.dtype)
    k = axis_angle / theta
    kx = torch.tensor([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]], dtype=k.dtype)
    return torch.eye(3, dtype=k.dtype) + math.sin(theta) * kx + (1 - math.cos(theta)) * kx @ kx


def random_scene(
    n: int,
    width: int = 320,
    height: int = 240,
    seed: int = 0,
    dtype: torch.dtype = torch.float32,
    device: str | torch.device = "cpu",
    depth_range: tuple[float, float] = (2.0, 6.0),
    scale_range: tuple[float, float] = (0.005, 0.05),
) -> Scene:
    """A seeded random scene of ``n`` Gaussians in front of a ``width`` x ``height`` camera."""
    g = torch.Generator().manual_seed(seed)
    f = 0.8 * width
    K = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], dtype=torch.float64)
    z = torch.empty(n, dtype=torch.float64).uniform_(*depth_range, generator=g)
    u = (torch.rand(n, generator=g, dtype=torch.float64) * 1.1 - 0.55) * width / f
    v = (torch.rand(n, generator=g, dtype=torch.float64) * 1.1 - 0.55) * height / f
    p_cam = torch.stack([u * z, v * z, z], dim=1)
    R = _rotation(torch.randn(3, generator=g, dtype=torch.float64) * 0.3)
    t = torch.randn(3, generator=g, dtype=torch.float64)
    viewmat = torch.eye(4, dtype=torch.float64)
    viewmat[:3, :3], viewmat[:3, 3] = R, t
    means = (p_cam - t) @ R  # invert p_cam = R p_world + t
    lo, hi = math.log(scale_range[0]), math.log(scale_range[1])
    scales = torch.exp(torch.empty(n, 3, dtype=torch.float64).uniform_(lo, hi, generator=g))
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=g, dtype=torch.float64), dim=1)
    opacities = torch.empty(n, dtype=torch.float64).uniform_(0.05, 1.0, generator=g)
    colors = torch.rand(n, 3, generator=g, dtype=torch.float64)
    conv = dict(dtype=dtype, device=device)
    return Scene(
        means.to(**conv), quats.to(**conv), scales.to(**conv), opacities.to(**conv),
        colors.to(**conv), viewmat.to(**conv), K.to(**conv), width, height,
    )
