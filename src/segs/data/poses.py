"""Pose utilities for ground truth: quaternions, checks and interpolation (numpy only).

Quaternions are [..., 4] in (x, y, z, w) order (TUM's); EuRoC's (w, x, y, z) is reordered by its
reader. Poses are [4,4] float64 homogeneous matrices.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from segs.errors import DataError

QUAT_TOLERANCE = 1e-3  # accepted | |q| - 1 |; larger means a corrupt file, not rounding
RIGID_TOLERANCE = 1e-3  # accepted deviation of R R^T from I and of the last row from 0 0 0 1


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Unit quaternions [N,4] (x, y, z, w) -> rotations [N,3,3]."""
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
        2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
        2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
    ], -1).reshape(q.shape[:-1] + (3, 3))


def matrix_to_quat(r: np.ndarray) -> np.ndarray:
    """Rotations [N,3,3] -> unit quaternions [N,4] (x, y, z, w), w >= 0."""
    r = np.asarray(r, np.float64).reshape(-1, 3, 3)
    xx, xy, xz, yx, yy, yz, zx, zy, zz = (r[:, i, j] for i in range(3) for j in range(3))
    m = np.stack([  # symmetric 4x4 whose top eigenvector is the quaternion (Bar-Itzhack)
        [xx - yy - zz, yx + xy, zx + xz, zy - yz],
        [yx + xy, yy - xx - zz, zy + yz, xz - zx],
        [zx + xz, zy + yz, zz - xx - yy, yx - xy],
        [zy - yz, xz - zx, yx - xy, xx + yy + zz],
    ]).transpose(2, 0, 1) / 3.0
    q = np.linalg.eigh(m)[1][:, :, -1]
    return q * np.where(q[:, 3:] < 0, -1.0, 1.0)


def poses_from_tq(t: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Translations [N,3] and quaternions [N,4] (x, y, z, w) -> poses [N,4,4]."""
    out = np.tile(np.eye(4), (len(t), 1, 1))
    out[:, :3, :3] = quat_to_matrix(q)
    out[:, :3, 3] = t
    return out


def check_quaternions(q: np.ndarray, path: Path, linenos: list[int]) -> None:
    """DataError naming file and line of the first quaternion [N,4] whose norm is not 1 +- 1e-3."""
    bad = np.flatnonzero(np.abs(np.linalg.norm(q, axis=1) - 1.0) > QUAT_TOLERANCE)
    if len(bad):
        norm = np.linalg.norm(q[bad[0]])
        raise DataError(f"{path}:{linenos[bad[0]]}: quaternion norm {norm:.6g}, expected a unit quaternion")


def check_rigid(poses: np.ndarray, path: Path, linenos: list[int] | None = None, what: str = "") -> None:
    """DataError naming the file (and line, or `what`) of the first [4,4] pose that is not rigid."""
    rot = poses[:, :3, :3]
    ortho = np.abs(rot @ rot.transpose(0, 2, 1) - np.eye(3)).max(axis=(1, 2))
    bottom = np.abs(poses[:, 3] - [0, 0, 0, 1]).max(axis=1)
    bad = np.flatnonzero((ortho > RIGID_TOLERANCE) | (bottom > RIGID_TOLERANCE) | (np.linalg.det(rot) < 0))
    if len(bad):
        where = f"{path}:{linenos[bad[0]]}" if linenos else f"{path}: {what}".rstrip()
        raise DataError(f"{where}: expected a rigid 4x4 transform (orthonormal rotation, last row 0 0 0 1)")


def slerp(q0: np.ndarray, q1: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Spherical interpolation of unit quaternions [N,4] at fractions a [N] in [0,1]."""
    dot = np.sum(q0 * q1, axis=-1)
    q1 = np.where(dot[:, None] < 0, -q1, q1)
    dot = np.clip(np.abs(dot), -1.0, 1.0)
    theta = np.arccos(dot)
    small = theta < 1e-6
    sin = np.where(small, 1.0, np.sin(theta))
    w0 = np.where(small, 1 - a, np.sin((1 - a) * theta) / sin)
    w1 = np.where(small, a, np.sin(a * theta) / sin)
    q = w0[:, None] * q0 + w1[:, None] * q1
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def interpolate_poses(times: np.ndarray, poses: np.ndarray, query: np.ndarray,
                      max_difference: float) -> np.ndarray:
    """Poses [M,4,4] sampled at increasing times [M], evaluated at query times [N] -> [N,4,4].

    A query between two samples that are both within max_difference seconds is interpolated
    (SLERP of the rotation, linear translation); otherwise the nearest sample is used if it is
    within max_difference; otherwise the result is NaN.
    """
    out = np.full((len(query), 4, 4), np.nan)
    if len(times) == 0 or len(query) == 0:
        return out
    if len(times) == 1:  # a single sample: nearest only
        times, poses = np.repeat(times, 2), np.repeat(poses, 2, axis=0)
    right = np.clip(np.searchsorted(times, query), 1, max(len(times) - 1, 1))
    left = right - 1
    dl, dr = np.abs(query - times[left]), np.abs(times[right] - query)
    nearest = np.where(dl <= dr, left, right)
    near_ok = np.minimum(dl, dr) <= max_difference
    out[near_ok] = poses[nearest[near_ok]]
    between = (times[left] < query) & (query < times[right]) & (dl <= max_difference) & (dr <= max_difference)
    if between.any():
        l, r = left[between], right[between]
        a = (query[between] - times[l]) / (times[r] - times[l])
        q = slerp(matrix_to_quat(poses[l, :3, :3]), matrix_to_quat(poses[r, :3, :3]), a)
        pose = poses_from_tq((1 - a)[:, None] * poses[l, :3, 3] + a[:, None] * poses[r, :3, 3], q)
        out[between] = pose
    return out
