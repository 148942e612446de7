"""Vectorized ORB matching: by projection on a keypoint grid, by descriptors, for triangulation.

All searches produce candidate pairs (query, keypoint) with numpy, compute Hamming distances in one
go and resolve best / second best / one-to-one with sorts, never a per-feature Python loop.
Thresholds follow ORB-SLAM: TH_HIGH 100, TH_LOW 50, nearest-neighbour ratios 0.6 to 0.9.
"""
from __future__ import annotations

import cv2
import numpy as np

from segs.slam.features.extractor import hamming_pairs
from segs.slam.native import kernels
from segs.slam.estimation.optimize import CHI2_MONO, CHI2_STEREO

TH_HIGH = 100
TH_LOW = 50
# chi-square 95 % quantile, 1 dof (a statistics constant, not a parameter): the epipolar-distance
# test of triangulation matches
CHI2_EPIPOLAR = 3.84


def best_two(q: np.ndarray, k: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, ...]:
    """Per query: best pair index and second distance.

    q, k, d [P] candidate pairs -> (queries [Q], best keypoint [Q], best dist [Q], second dist [Q]
    (inf if none), position of the best pair in the input [Q]).
    """
    if len(q) == 0:
        e = np.zeros(0, np.int64)
        return e, e, e, np.zeros(0), e
    order = np.lexsort((d, q))
    qs = q[order]
    first = np.r_[True, qs[1:] != qs[:-1]]
    pos = np.flatnonzero(first)
    nxt = pos + 1
    has2 = np.zeros(len(pos), bool)
    has2[nxt < len(qs)] = qs[np.minimum(nxt, len(qs) - 1)][nxt < len(qs)] == qs[pos][nxt < len(qs)]
    d2 = np.full(len(pos), np.inf)
    d2[has2] = d[order[nxt[has2]]]
    b = order[pos]
    return q[b], k[b], d[b], d2, b


def unique_targets(q: np.ndarray, k: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Mask keeping, for each target k, only its lowest-distance pair (one-to-one matches)."""
    keep = np.zeros(len(k), bool)
    if len(k):
        order = np.lexsort((d, k))
        ks = k[order]
        keep[order[np.r_[True, ks[1:] != ks[:-1]]]] = True
    return keep


def rotation_consistent(angle_a: np.ndarray, angle_b: np.ndarray, bins: int = 30,
                        min_share: float = 0.1) -> np.ndarray:
    """Mask of matches whose orientation change lies in the three dominant histogram bins [P]
    (ORB-SLAM's HISTO_LENGTH 30 bins; the second and third count if they hold at least min_share
    of the first's matches, ComputeThreeMaxima's 0.1)."""
    if len(angle_a) == 0:
        return np.zeros(0, bool)
    rot = np.mod(angle_a.astype(np.float64) - angle_b.astype(np.float64), 360.0)
    b = np.minimum((rot * bins / 360.0).astype(np.int64), bins - 1)
    h = np.bincount(b, minlength=bins)
    top = np.argsort(-h, kind="stable")[:3]
    keep_bins = [top[0]] + [t for t in top[1:] if h[t] >= min_share * h[top[0]]]
    return np.isin(b, keep_bins)


def search_projection(frame, uv: np.ndarray, desc: np.ndarray, level: np.ndarray, radius: np.ndarray,
                      lo: np.ndarray, hi: np.ndarray, ur: np.ndarray | None = None,
                      max_dist: int = TH_HIGH, ratio: float = 0.8, only_free: bool = True,
                      angle: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Match projected points to a frame's keypoints.

    frame: SlamFrame or KeyFrame (kp, grid, ur, points); uv [M,2] projections; desc [M,32];
    level [M] predicted level; radius [M] pixels; lo/hi [M] allowed keypoint octaves; ur [M]
    predicted right coordinate (checked against keypoints with depth), or None; angle [M]
    orientation of the source keypoints for the rotation-consistency check, or None.
    Returns (query indices [Q], keypoint indices [Q]).
    """
    q, k, d1, d2 = nearest_two_in_radius(frame, uv, desc, radius, lo, hi, ur, only_free)
    # ORB-SLAM applies the ratio only when best and second are on the same level; here always
    # (stricter), a missing second candidate passes
    ok = (d1 <= max_dist) & (d1 <= ratio * d2)
    q, k, d1 = q[ok], k[ok], d1[ok]
    keep = unique_targets(q, k, d1)
    q, k = q[keep], k[keep]
    if angle is not None and len(q):
        keep = rotation_consistent(angle[q], frame.kp.angle[k])
        q, k = q[keep], k[keep]
    return q, k


def nearest_two_in_radius(frame, uv: np.ndarray, desc: np.ndarray, radius: np.ndarray, lo: np.ndarray,
                          hi: np.ndarray, ur: np.ndarray | None, only_free: bool, gate: tuple | None = None,
                          native: bool = True) -> tuple[np.ndarray, ...]:
    """Per query, the nearest and second-nearest keypoint (Hamming) among the frame's keypoints
    within `radius` pixels of uv whose octave lies in [lo, hi] (free ones only if only_free; with
    ur, a keypoint with depth must lie within the radius of ur in the right image too).

    gate: (z [M] query depths, sigma2 [levels], ur_sigma or None, bf): candidates must also pass
    the reprojection chi-square test (5.991 / 7.815 with depth) of local mapping's fusion.
    Shapes as in search_projection -> (queries [Q] ascending, keypoint [Q], distance [Q] int64,
    second distance [Q] float64, inf if none). native: the C++ kernel where it is built (same
    results), else numpy.
    """
    ext = kernels() if native else None
    if ext is not None and len(uv) and len(frame.kp):
        g, i64, none = frame.grid, np.int64, np.zeros(0)
        z, sigma2, ur_sigma, bf = gate if gate is not None else (none, np.ones(1), None, 0.0)
        return ext.best_two_in_radius(
            g.start, g.order, frame.kp.uv, frame.kp.octave, frame.kp.desc,
            frame.points if only_free else np.zeros(0, i64),
            frame.ur if ur is not None or gate is not None else none,
            g.cell, g.nx, g.ny, uv, np.broadcast_to(np.asarray(radius, float), (len(uv),)),
            np.asarray(lo, i64), np.asarray(hi, i64), ur if ur is not None else none, desc,
            z, sigma2, 0.0 if ur_sigma is None else 1.0 / ur_sigma ** 2, float(bf), CHI2_MONO, CHI2_STEREO)
    qi, ki = frame.grid.query(uv, radius)
    oct_ = frame.kp.octave[ki]
    ok = (oct_ >= lo[qi]) & (oct_ <= hi[qi])
    if only_free:
        ok &= frame.points[ki] < 0
    if ur is not None:
        fur = frame.ur[ki]
        ok &= (fur < 0) | (np.abs(ur[qi] - fur) <= radius[qi])
    if gate is not None:
        z, sigma2, ur_sigma, bf = gate
        e2 = ((uv[qi] - frame.kp.uv[ki]) ** 2).sum(1) / sigma2[oct_]
        st = frame.ur[ki] >= 0
        w_ur = 1.0 / sigma2[oct_] if ur_sigma is None else 1.0 / ur_sigma ** 2
        disp = frame.kp.uv[ki, 0] - frame.ur[ki]
        e2 = e2 + np.where(st, (bf / np.maximum(z[qi], 1e-9) - disp) ** 2, 0) * w_ur
        ok &= e2 < np.where(st, CHI2_STEREO, CHI2_MONO)
    qi, ki = qi[ok], ki[ok]
    d = hamming_pairs(desc, qi, frame.kp.desc, ki)
    q, k, d1, d2, _ = best_two(qi, ki, d)
    return q, k, d1, d2


def match_descriptors(da: np.ndarray, db: np.ndarray, ratio: float = 0.75,
                      max_dist: int = TH_LOW) -> tuple[np.ndarray, np.ndarray]:
    """Brute-force kNN (cv2, Hamming) with ratio test and mutual uniqueness -> (ia [K], ib [K])."""
    if len(da) < 2 or len(db) < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    dist, nidx = knn_hamming(da, db, 2)
    ok = (nidx[:, 1] >= 0) & (dist[:, 0] <= max_dist) & (dist[:, 0] < ratio * dist[:, 1])
    ia = np.flatnonzero(ok)
    ib, d = nidx[ok, 0].astype(np.int64), dist[ok, 0]
    keep = unique_targets(ia, ib, d)
    return ia[keep], ib[keep]


def knn_hamming(da: np.ndarray, db: np.ndarray, k: int, native: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """The k nearest descriptors of db for each of da (Hamming), as numpy arrays.

    cv2.batchDistance is the kNN search inside cv2.BFMatcher.knnMatch (same neighbours, same
    order, ties included) without one DMatch object per pair. -> (distances [A,k'] int32,
    indices into db [A,k'] int32, -1 where there is no neighbour), k' = min(k, len(db)).
    native: the C++ kernel where it is built (the same selection, entry for entry, at about twice
    batchDistance's speed: its per-pair function call costs more than the 4 popcounts).
    """
    ext = kernels() if native else None
    if ext is not None and len(da) and len(db):
        return ext.knn_hamming(np.ascontiguousarray(da, np.uint8), np.ascontiguousarray(db, np.uint8), int(k))
    dist, nidx = cv2.batchDistance(np.ascontiguousarray(da), np.ascontiguousarray(db), cv2.CV_32S,
                                   normType=cv2.NORM_HAMMING, K=k, update=0, crosscheck=False)
    return dist, nidx


def _knn_by_node(da: np.ndarray, na: np.ndarray, db: np.ndarray, nb: np.ndarray,
                 k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """knn_hamming of da [A,32] against the db [B,32] under the same node (na [A], nb [B]) ->
    (rows of da [P], rows of db [P], distances [P] float64), query-major, nearest first."""
    qs, ts, ds = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)], [np.zeros(0)]
    oa, ob = np.argsort(na, kind="stable"), np.argsort(nb, kind="stable")
    ua, sa = np.unique(na[oa], return_index=True)
    ub, sb = np.unique(nb[ob], return_index=True)
    ea, eb = np.r_[sa[1:], len(oa)], np.r_[sb[1:], len(ob)]
    _, ia, ib = np.intersect1d(ua, ub, return_indices=True)
    for x, y in zip(ia.tolist(), ib.tolist()):
        a, b = oa[sa[x]:ea[x]], ob[sb[y]:eb[y]]
        dist, nidx = knn_hamming(da[a], db[b], k)
        found = nidx >= 0
        qs.append(a[np.nonzero(found)[0]])
        ts.append(b[nidx[found]])
        ds.append(dist[found].astype(np.float64))
    q, t, d = np.concatenate(qs), np.concatenate(ts), np.concatenate(ds)
    order = np.lexsort((d, q))
    return q[order], t[order], d[order]


def match_frame_to_kf(frame, kf, valid: np.ndarray, ratio: float = 0.75,
                      max_dist: int = TH_LOW) -> tuple[np.ndarray, np.ndarray]:
    """Frame keypoints vs kf's keypoints that carry a valid map point.

    valid: Map.valid array. Returns (frame keypoint idx [K], map point ids [K]).
    """
    kidx = np.flatnonzero(kf.points >= 0)
    kidx = kidx[valid[kf.points[kidx]]]
    if len(kidx) < 2 or len(frame.kp) < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    fi, ki = match_descriptors(frame.kp.desc, kf.kp.desc[kidx], ratio, max_dist)
    keep = rotation_consistent(frame.kp.angle[fi], kf.kp.angle[kidx[ki]])
    fi, ki = fi[keep], ki[keep]
    return fi, kf.points[kidx[ki]]


def match_for_triangulation(kf1, kf2, F12: np.ndarray, sigma2: np.ndarray, ratio: float = 0.6,
                            max_dist: int = TH_LOW, epi_chi2: float = CHI2_EPIPOLAR,
                            knn: int = 8, nodes: tuple[np.ndarray, np.ndarray] | None = None
                            ) -> tuple[np.ndarray, np.ndarray]:
    """Unmatched keypoints of kf1 vs kf2 satisfying the epipolar constraint.

    F12 [3,3]: x2^T F12 x1 = 0; knn: descriptor candidates per keypoint tried against the epipolar
    line; nodes: vocabulary-tree node per keypoint of kf1 [N1] and kf2 [N2], candidates only
    under the same node (None: every pair). Returns (idx1 [K], idx2 [K]).
    """
    i1 = np.flatnonzero(kf1.points < 0)
    i2 = np.flatnonzero(kf2.points < 0)
    if len(i1) == 0 or len(i2) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    # descriptors first (cv2 kNN on the free keypoints), then the epipolar test on the survivors
    if nodes is None:
        dist, nidx = knn_hamming(kf1.kp.desc[i1], kf2.kp.desc[i2], knn)
        found = nidx >= 0  # [N1,k] in query-major, nearest-first order
        q = np.nonzero(found)[0].astype(np.int64)
        t, d = nidx[found].astype(np.int64), dist[found].astype(np.float64)
    else:
        q, t, d = _knn_by_node(kf1.kp.desc[i1], nodes[0][i1], kf2.kp.desc[i2], nodes[1][i2], knn)
    if len(q) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    x1 = np.c_[kf1.kp.uv[i1[q]], np.ones(len(q))]
    x2 = np.c_[kf2.kp.uv[i2[t]], np.ones(len(q))]
    line = x1 @ F12.T  # epipolar lines in image 2
    num = (line * x2).sum(1)
    dist2 = num ** 2 / np.maximum(line[:, 0] ** 2 + line[:, 1] ** 2, 1e-12)
    ok = (dist2 < epi_chi2 * sigma2[kf2.kp.octave[i2[t]]]) & (d <= max_dist)
    q, t, d = q[ok], t[ok], d[ok]
    qq, tt, d1, d2, _ = best_two(q, t, d)
    ok = d1 < ratio * d2 if ratio < 1.0 else np.ones(len(qq), bool)
    qq, tt, d1 = qq[ok], tt[ok], d1[ok]
    keep = unique_targets(qq, tt, d1)
    qq, tt = qq[keep], tt[keep]
    keep = rotation_consistent(kf1.kp.angle[i1[qq]], kf2.kp.angle[i2[tt]])
    return i1[qq[keep]], i2[tt[keep]]
