"""SEPM: structure-enhanced photorealistic mapping — anchors from the SLAM point cloud.

Each batch of new SLAM points P is voxelized, V = unique(round(P / eps)) * eps (the paper's
Eq. 6), and voxels that already hold an anchor are dropped (the paper's {.}; the authors' code
skips this de-duplication, we do not). New anchors get log-scales from the mean squared
distance to their 3 nearest anchors, zero offsets and zero features.
"""
from __future__ import annotations

import torch

from segs.modules.geometry import knn_mean_sq_dist


def voxel_keys(points: torch.Tensor, eps: float) -> torch.Tensor:
    """Integer voxel coordinates round(P / eps) of points [M,3] -> [M,3] int64."""
    return torch.round(points.double() / eps).to(torch.int64)


def _hash(keys: torch.Tensor) -> torch.Tensor:
    """[M,3] int64 voxel coordinates -> [M] int64 keys (exact for |coord| < 2^20)."""
    k = keys + (1 << 20)
    return (k[:, 0] << 42) | (k[:, 1] << 21) | k[:, 2]


def voxelize(points: torch.Tensor, eps: float, existing: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Voxel centres of points [M,3] not already occupied by `existing` [N,3] anchors.

    Returns (centres [V,3] in points' dtype, index [M] long: the output row of each input point, -1 for
    points whose voxel already held an anchor).
    """
    if eps <= 0:
        raise ValueError(f"voxel size must be > 0, got {eps}")
    if points.shape[0] == 0:
        return points.new_zeros((0, 3)), torch.zeros(0, dtype=torch.long, device=points.device)
    keys = voxel_keys(points, eps)
    uniq, inverse = torch.unique(_hash(keys), return_inverse=True)
    first = torch.full((uniq.shape[0],), keys.shape[0], dtype=torch.long, device=points.device)
    first = first.scatter_reduce(0, inverse, torch.arange(keys.shape[0], device=points.device), reduce="amin")
    cells = keys[first]
    new = torch.ones(uniq.shape[0], dtype=torch.bool, device=points.device)
    if existing is not None and existing.shape[0]:
        new = ~torch.isin(uniq, _hash(voxel_keys(existing, eps)))
    remap = torch.full((uniq.shape[0],), -1, dtype=torch.long, device=points.device)
    remap[new] = torch.arange(int(new.sum()), device=points.device)
    return (cells[new].double() * eps).to(points.dtype), remap[inverse]


def initial_log_scales(new: torch.Tensor, existing: torch.Tensor, k: int = 3) -> torch.Tensor:
    """log(sqrt(mean squared distance to the k nearest anchors)) repeated to [M,6]."""
    d2 = knn_mean_sq_dist(new, torch.cat([existing, new]), k).to(new)
    return torch.log(torch.sqrt(d2)).unsqueeze(1).repeat(1, 6)
