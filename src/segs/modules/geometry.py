"""Small geometric helpers of the mapper: similarities, quaternions, nearest neighbours."""
from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation


def split_similarity(T: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, float]:
    """Similarity [4,4] = [s R | t] -> (R [3,3], t [3], s)."""
    a = T[:3, :3]
    s = float(torch.linalg.det(a).abs() ** (1.0 / 3.0))
    return a / s, T[:3, 3], s


def apply_similarity(T: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """points [N,3] -> T applied (s R p + t)."""
    return points @ T[:3, :3].T.to(points.dtype) + T[:3, 3].to(points.dtype)


def rotmat_to_quat(R: torch.Tensor) -> torch.Tensor:
    """[3,3] rotation -> [4] wxyz quaternion (w >= 0), in R's dtype and on its device."""
    x, y, z, w = Rotation.from_matrix(R.detach().cpu().double().numpy()).as_quat()
    q = torch.tensor([w, x, y, z], dtype=R.dtype, device=R.device)
    return q if q[0] >= 0 else -q


def quat_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product of wxyz quaternions a [...,4] and b [...,4]."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        -1,
    )


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """Unit wxyz quaternions [N,4] -> rotation matrices [N,3,3]."""
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        -1,
    ).reshape(*q.shape[:-1], 3, 3)  # fmt: skip


def knn_mean_sq_dist(query: torch.Tensor, reference: torch.Tensor, k: int = 3) -> torch.Tensor:
    """Mean squared distance of each query point [M,3] to its k nearest reference points [R,3].

    A query point that is itself in reference is not its own neighbour (distance 0 skipped).
    Returns [M] in query's dtype, on its device (a large value when the reference has no other point).
    """
    ref = reference.detach().cpu().double().numpy()
    q = query.detach().cpu().double().numpy()
    if len(ref) == 0 or len(q) == 0:
        return torch.full((len(q),), 1e-2, dtype=query.dtype, device=query.device)
    kk = min(k + 1, len(ref))
    dist, _ = cKDTree(ref).query(q, k=kk)
    dist = np.asarray(dist, np.float64).reshape(len(q), kk)
    dist = np.sort(np.where(dist > 1e-9, dist, np.inf), axis=1)[:, :k]
    finite = np.isfinite(dist)
    n = finite.sum(1)
    mean = np.where(n > 0, np.where(finite, dist**2, 0.0).sum(1) / np.maximum(n, 1), 1e-2)
    return torch.from_numpy(np.maximum(mean, 1e-14)).to(query)
