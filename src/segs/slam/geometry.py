"""Small vectorized geometry helpers: poses (w2c 4x4), projection, alignment, index ranges."""
from __future__ import annotations

import cv2
import numpy as np


def expand_ranges(starts: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Flatten ranges [starts[i], starts[i]+counts[i]) -> (owner i [T], value [T])."""
    counts = np.maximum(np.asarray(counts, np.int64), 0)
    total = int(counts.sum())
    owner = np.repeat(np.arange(len(counts)), counts)
    offs = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)
    return owner, np.asarray(starts, np.int64)[owner] + offs


def inv_se3(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid [4,4] transform."""
    R, t = T[:3, :3], T[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


def orthonormalize(T: np.ndarray) -> np.ndarray:
    """Rigid [4,4] with its rotation projected back onto SO(3) (compositions drift numerically)."""
    U, _, Vt = np.linalg.svd(T[:3, :3])
    R = U @ Vt
    if np.linalg.det(R) < 0:
        R = U @ np.diag([1.0, 1.0, -1.0]) @ Vt
    out = np.eye(4)
    out[:3, :3] = R
    out[:3, 3] = T[:3, 3]
    return out


def inv_sim3(S: np.ndarray) -> np.ndarray:
    """Inverse of a similarity [4,4] [[sR, t],[0,1]]."""
    return np.linalg.inv(S)


def cam_center(w2c: np.ndarray) -> np.ndarray:
    """Camera centre [3] in the world of a w2c [4,4]."""
    return -w2c[:3, :3].T @ w2c[:3, 3]


def transform(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Apply [4,4] to points [N,3] -> [N,3]."""
    return p @ T[:3, :3].T + T[:3, 3]


def project(K: np.ndarray, pc: np.ndarray) -> np.ndarray:
    """Camera-frame points [N,3] -> pixels [N,2] (z must be > 0 to be meaningful)."""
    z = np.where(np.abs(pc[:, 2]) < 1e-12, 1e-12, pc[:, 2])
    return np.stack([K[0, 0] * pc[:, 0] / z + K[0, 2], K[1, 1] * pc[:, 1] / z + K[1, 2]], 1)


def rt_to_w2c(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rvec, np.float64).reshape(3, 1))[0]
    T[:3, 3] = np.asarray(tvec, np.float64).ravel()
    return T


def w2c_to_rt(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return cv2.Rodrigues(np.ascontiguousarray(T[:3, :3]))[0], T[:3, 3].reshape(3, 1).copy()


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool) -> np.ndarray:
    """Similarity [4,4] S minimising |dst - S src|^2 for src, dst [N,3] (Umeyama 1991)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    U, D, Vt = np.linalg.svd(cov)
    E = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        E[2, 2] = -1
    R = U @ E @ Vt
    var_s = (xs ** 2).sum() / len(src)
    s = float(np.trace(np.diag(D) @ E) / var_s) if with_scale and var_s > 0 else 1.0
    S = np.eye(4)
    S[:3, :3] = s * R
    S[:3, 3] = mu_d - s * R @ mu_s
    return S


def sim3_scale(S: np.ndarray) -> float:
    return float(np.cbrt(np.linalg.det(S[:3, :3])))


def skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def fundamental(w2c1: np.ndarray, w2c2: np.ndarray, K: np.ndarray) -> np.ndarray:
    """F [3,3] with x2^T F x1 = 0 for pixels x1 in camera 1 and x2 in camera 2."""
    T21 = w2c2 @ inv_se3(w2c1)
    E = skew(T21[:3, 3]) @ T21[:3, :3]
    Ki = np.linalg.inv(K)
    return Ki.T @ E @ Ki


def sampson_distance(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Sampson distance [N] (pixels) of pixel matches x1 -> x2 [N,2] under F [3,3] (x2^T F x1 = 0):
    the first-order geometric distance of the pair to the epipolar constraint."""
    h1, h2 = np.c_[x1, np.ones(len(x1))], np.c_[x2, np.ones(len(x2))]
    l2, l1 = h1 @ F.T, h2 @ F  # epipolar lines in image 2, and in image 1
    num = (h2 * l2).sum(1) ** 2
    return np.sqrt(num / (l2[:, 0] ** 2 + l2[:, 1] ** 2 + l1[:, 0] ** 2 + l1[:, 1] ** 2))


def triangulate(P1: np.ndarray, P2: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Linear triangulation (cv2) of pixel pairs x1, x2 [N,2] with 3x4 projections -> [N,3]."""
    X = cv2.triangulatePoints(P1, P2, x1.T.astype(np.float64), x2.T.astype(np.float64))
    w = X[3]
    w = np.where(np.abs(w) < 1e-12, 1e-12, w)
    return (X[:3] / w).T
