"""EWA projection of 3D Gaussians to screen space (differentiable, pure PyTorch).

Shared by the ``torch`` and ``cpu`` backends; autograd provides its backward. Conventions follow
gsplat / 3D-GS: world-to-camera ``viewmat``, wxyz quaternions (normalised here), pixel centres at
``(x + 0.5, y + 0.5)``, covariance dilated by ``eps2d`` pixels^2 (default :data:`EPS2D`), 3-sigma screen radius.
"""
from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F

EPS2D = 0.3  # default low-pass filter added to the 2D covariance (pixels^2), as in 3D-GS
SIGMA_EXTENT = 3.0  # screen-space radius = ceil(3 * sqrt(largest eigenvalue))
FOV_MARGIN = 0.3  # Jacobian clamp: 30 % of the half field of view beyond the image border


class Projected(NamedTuple):
    """Screen-space Gaussians.

    means2d [N,2] pixel coordinates; conics [N,3] upper triangle (a, b, c) of the inverse 2D
    covariance; depths [N] camera z; radii [N] int32 pixels, 0 = culled (not drawn).
    """

    means2d: torch.Tensor
    conics: torch.Tensor
    depths: torch.Tensor
    radii: torch.Tensor


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """[N,4] wxyz (any norm) -> [N,3,3] rotation matrices."""
    w, x, y, z = F.normalize(quats, dim=-1).unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]
    return torch.stack(rows, dim=-1).reshape(quats.shape[:-1] + (3, 3))


def covariances(quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """World covariances R S S^T R^T: quats [N,4], scales [N,3] -> [N,3,3]."""
    m = quat_to_rotmat(quats) * scales[:, None, :]
    return m @ m.transpose(1, 2)


def _jacobian(p: torch.Tensor, K: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """Perspective Jacobian [N,2,3] at camera points p [N,3] (z > 0), x/z clamped like 3D-GS."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    x, y, z = p.unbind(-1)
    lim_x_pos = (width - cx) / fx + FOV_MARGIN * 0.5 * width / fx
    lim_x_neg = cx / fx + FOV_MARGIN * 0.5 * width / fx
    lim_y_pos = (height - cy) / fy + FOV_MARGIN * 0.5 * height / fy
    lim_y_neg = cy / fy + FOV_MARGIN * 0.5 * height / fy
    tx = z * torch.minimum(torch.maximum(x / z, -lim_x_neg), lim_x_pos)
    ty = z * torch.minimum(torch.maximum(y / z, -lim_y_neg), lim_y_pos)
    zero = torch.zeros_like(z)
    rows = [fx / z, zero, -fx * tx / (z * z), zero, fy / z, -fy * ty / (z * z)]
    return torch.stack(rows, dim=-1).reshape(-1, 2, 3)


@torch.no_grad()
def _radii(cov2d: torch.Tensor, det: torch.Tensor, means2d, valid, width, height) -> torch.Tensor:
    """3-sigma integer radius of the dilated 2D covariance; 0 where culled."""
    mid = 0.5 * (cov2d[:, 0, 0] + cov2d[:, 1, 1])
    lam = mid + torch.sqrt(torch.clamp(mid * mid - det, min=0.1))
    radius = torch.ceil(SIGMA_EXTENT * torch.sqrt(lam))
    u, v = means2d[:, 0], means2d[:, 1]
    inside = (u + radius > 0) & (u - radius < width) & (v + radius > 0) & (v - radius < height)
    keep = valid & (det > 0) & inside
    return torch.where(keep, radius, torch.zeros_like(radius)).to(torch.int32)


def project(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    viewmat: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    near: float,
    far: float,
    eps2d: float = EPS2D,
) -> Projected:
    """Project Gaussians (means [N,3], quats [N,4], scales [N,3]) through viewmat [4,4], K [3,3];
    eps2d (pixels^2) is added to the diagonal of each 2D covariance (the low-pass filter).

    Gaussians with camera z outside [near, far], a degenerate 2D covariance or a footprint fully
    outside the image get radius 0; their other outputs are finite (never nan/inf) but unused.
    """
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    p = means @ R.T + t
    z = p[:, 2]
    in_depth = (z >= near) & (z <= far)
    # Culled points get z = 1 so that nothing below divides by ~0 (gradients stay finite).
    z_safe = torch.where(in_depth, z, torch.ones_like(z))
    p_safe = torch.cat([p[:, :2], z_safe[:, None]], dim=1)
    cov_cam = R @ covariances(quats, scales) @ R.T
    J = _jacobian(p_safe, K, width, height)
    cov2d = J @ cov_cam @ J.transpose(1, 2)
    cov2d = cov2d + eps2d * torch.eye(2, dtype=cov2d.dtype, device=cov2d.device)
    a, b, c = cov2d[:, 0, 0], 0.5 * (cov2d[:, 0, 1] + cov2d[:, 1, 0]), cov2d[:, 1, 1]
    det = a * c - b * b
    det_safe = torch.where(det > 0, det, torch.ones_like(det))
    conics = torch.stack([c / det_safe, -b / det_safe, a / det_safe], dim=-1)
    u = K[0, 0] * p_safe[:, 0] / z_safe + K[0, 2]
    v = K[1, 1] * p_safe[:, 1] / z_safe + K[1, 2]
    means2d = torch.stack([u, v], dim=-1)
    radii = _radii(cov2d, det, means2d, in_depth, width, height)
    return Projected(means2d, conics, z, radii)
