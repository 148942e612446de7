"""Map initialization.

RGB-D / stereo: one frame with enough keypoints with depth (back-projected; see `Tracker`); where
no frame has enough, the two-view start below scaled to metres by the depth its points have.
Monocular: two views. A reference frame waits for a partner; their ORB matches feed a homography
and an essential matrix (OpenCV MAGSAC++); ORB-SLAM's symmetric transfer scores choose the model
(R_H = S_H / (S_H + S_F) > 0.40 -> homography; a homography without a reconstruction falls back to
the fundamental matrix at a larger parallax), the model's motion hypotheses are triangulated and
the one that clearly explains most matches (in front of both cameras, or with nearly parallel
rays, small reprojection error) with enough parallax wins. The scale is arbitrary (normalised
later to a median depth of 1). The frames fed while the reference waited are kept (`waiting`):
the tracker poses them once the map exists.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from segs.slam.config import InitConfig
from segs.slam.features.frame import SlamFrame
from segs.slam.estimation.matching import match_descriptors, rotation_consistent

TH_H = 5.991  # chi2 2 dof
TH_F = 3.841  # chi2 1 dof (point-to-line)
# rays closer than this cosine (0.36 degrees) are "parallel": not triangulated (ORB-SLAM's 0.99998)
MIN_COS_PARALLAX = 0.99998


@dataclass
class TwoViewResult:
    """w2c of the second view (the first is the identity), triangulated points [N,3] and the
    keypoint indices [N] of each point in the reference and the current frame."""

    w2c: np.ndarray
    points: np.ndarray
    idx_ref: np.ndarray
    idx_cur: np.ndarray
    model: str


class MonoInitializer:
    def __init__(self, cfg: InitConfig, K: np.ndarray, sigma2: np.ndarray, seed: int = 0):
        self.cfg = cfg
        self.K = K
        self.sigma2 = sigma2
        self.seed = seed
        self.ref: SlamFrame | None = None
        # frames fed since the reference (in order): tracked against the initial map afterwards
        self.waiting: list[SlamFrame] = []

    def reset(self) -> None:
        self.ref = None
        self.waiting = []

    def try_initialize(self, frame: SlamFrame) -> TwoViewResult | None:
        """Feed a frame; returns a result once two views give a sound reconstruction."""
        if self.ref is None or len(self.ref) < self.cfg.min_matches \
                or frame.index - self.ref.index > self.cfg.max_frames:
            self._set_ref(frame if len(frame) >= self.cfg.min_matches else None)
            return None
        i1, i2 = match_descriptors(self.ref.kp.desc, frame.kp.desc, ratio=0.9, max_dist=50)
        keep = rotation_consistent(self.ref.kp.angle[i1], frame.kp.angle[i2])
        i1, i2 = i1[keep], i2[keep]
        if len(i1) < self.cfg.min_matches:
            if len(i1) < self.cfg.min_matches // 2:
                self._set_ref(frame)
            else:
                self.waiting.append(frame)
            return None
        res = self.reconstruct(self.ref.kp.uv[i1], frame.kp.uv[i2], self.sigma2[self.ref.kp.octave[i1]])
        if res is None:
            self.waiting.append(frame)
            return None
        w2c, X, good = res
        return TwoViewResult(w2c, X[good], i1[good], i2[good], "")

    def _set_ref(self, frame: SlamFrame | None) -> None:
        self.ref = frame
        self.waiting = []

    # ------------------------------------------------------------------ two-view geometry
    def reconstruct(self, x1: np.ndarray, x2: np.ndarray, sig2: np.ndarray):
        """Pixel matches x1, x2 [N,2] -> (w2c of view 2, points [N,3], good mask [N]) or None."""
        cv2.setRNGSeed(self.seed)
        # Models by MAGSAC++ (OpenCV USAC: local optimisation and a final fit on all inliers),
        # not plain RANSAC: RANSAC's unrefined minimal-sample essential matrix at short baselines
        # was off by degrees in rotation and up to 90 degrees in translation direction (synthetic
        # loop, frames 0-2). Calibrated camera: the essential matrix by the 5-point algorithm;
        # its F = K^-T E K^-1 enters ORB-SLAM's model score. Inliers are then ORB-SLAM's: the
        # symmetric transfer errors under the chi2 thresholds, with the keypoints' octave sigmas.
        H, _ = cv2.findHomography(x1, x2, cv2.USAC_MAGSAC, np.sqrt(TH_H), maxIters=500, confidence=0.999)
        E, _ = cv2.findEssentialMat(x1, x2, self.K, cv2.USAC_MAGSAC, 0.999, np.sqrt(TH_F))
        if E is not None and E.shape[0] > 3:
            E = E[:3]
        Ki = np.linalg.inv(self.K)
        F = Ki.T @ E @ Ki if E is not None else None
        sh, mh = self._score_h(H, x1, x2, sig2) if H is not None else (0.0, None)
        sf, mf = self._score_f(F, x1, x2, sig2) if F is not None else (0.0, None)
        if sh + sf <= 0:
            return None
        rh = sh / (sh + sf)
        models = []
        chose_h = H is not None and rh > self.cfg.homography_ratio
        if chose_h:
            models.append((self._hyps_h, H, mh, False, self.cfg.min_parallax_deg))
        if F is not None:
            models.append((self._hyps_f, F, mf, True,
                           self.cfg.fallback_min_parallax_deg if chose_h else self.cfg.min_parallax_deg))
        # ORB-SLAM's choice; after a homography that yields nothing, the fundamental matrix at
        # init.fallback_min_parallax_deg (ours: rotation-dominant motion over a non-planar scene
        # often scores the homography best without it yielding a reconstruction, and a homography
        # that explains the matches as well as F says the translation is barely observed). Never
        # the homography after a rejected fundamental matrix: its decomposition fits the small
        # flows of far points with any translation (KITTI frames 0 / 1: 80 degrees off)
        for hyps, M, mask, by_triangulated, min_parallax in models:
            res = self._select(hyps(M), x1, x2, sig2, mask, by_triangulated, min_parallax)
            if res is not None:
                return res
        return None

    def _score_h(self, H, x1, x2, sig2) -> tuple[float, np.ndarray]:
        """ORB-SLAM's homography score and inlier mask [N] (both transfer errors under TH_H)."""
        inv = 1.0 / sig2
        p2 = cv2.perspectiveTransform(x1[None].astype(np.float64), H)[0]
        try:
            Hi = np.linalg.inv(H)
        except np.linalg.LinAlgError:
            return 0.0, np.zeros(len(x1), bool)
        p1 = cv2.perspectiveTransform(x2[None].astype(np.float64), Hi)[0]
        c1 = ((p2 - x2) ** 2).sum(1) * inv
        c2 = ((p1 - x1) ** 2).sum(1) * inv
        ok = (c1 < TH_H) & (c2 < TH_H)
        return float(((TH_H - c1) + (TH_H - c2))[ok].sum()), ok

    def _score_f(self, F, x1, x2, sig2) -> tuple[float, np.ndarray]:
        """ORB-SLAM's fundamental-matrix score and inlier mask [N] (point-to-line errors)."""
        inv = 1.0 / sig2
        h1 = np.c_[x1, np.ones(len(x1))]
        h2 = np.c_[x2, np.ones(len(x2))]
        l2 = h1 @ F.T
        l1 = h2 @ F
        n2 = (l2 * h2).sum(1)
        d2 = n2 ** 2 / np.maximum(l2[:, 0] ** 2 + l2[:, 1] ** 2, 1e-12) * inv
        d1 = n2 ** 2 / np.maximum(l1[:, 0] ** 2 + l1[:, 1] ** 2, 1e-12) * inv
        ok = (d1 < TH_F) & (d2 < TH_F)
        return float(((TH_H - d1) + (TH_H - d2))[ok].sum()), ok

    def _hyps_h(self, H) -> list[tuple[np.ndarray, np.ndarray]]:
        n, Rs, ts, _ = cv2.decomposeHomographyMat(H, self.K)
        return [(Rs[i], ts[i].ravel()) for i in range(n)]

    def _hyps_f(self, F) -> list[tuple[np.ndarray, np.ndarray]]:
        E = self.K.T @ F @ self.K  # back to the essential matrix
        R1, R2, t = cv2.decomposeEssentialMat(E)
        t = t.ravel()
        return [(R1, t), (R1, -t), (R2, t), (R2, -t)]

    def _select(self, hyps, x1, x2, sig2, inl, by_triangulated: bool, min_parallax: float):
        """The motion hypothesis (R, t) that clearly explains most inlier matches -> (w2c [4,4],
        points [N,3], triangulated mask [N]) or None (ORB-SLAM's CheckRT / ReconstructF rules).

        A match counts for a hypothesis when both its reprojection errors are under 4 sigma^2
        and, if its rays part by more than MIN_COS_PARALLAX, it lies in front of both cameras;
        matches whose rays are nearly parallel (far points, the focus of expansion of a forward
        motion) count but are not triangulated. The best must count at least 0.9 of the inliers
        and triangulate init.min_triangulated; no other may come within 0.7 of it (of its count,
        or with by_triangulated, of its triangulated matches); the 50th-largest parallax of the
        counted matches must reach min_parallax (degrees)."""
        K = self.K
        P1 = K @ np.c_[np.eye(3), np.zeros(3)]
        results = []
        for R, t in hyps:
            if np.linalg.norm(t) < 1e-9:
                continue
            t = t / np.linalg.norm(t)
            P2 = K @ np.c_[R, t]
            Xh = cv2.triangulatePoints(P1, P2, x1.T.astype(np.float64), x2.T.astype(np.float64))
            X = (Xh[:3] / np.where(np.abs(Xh[3]) < 1e-12, 1e-12, Xh[3])).T
            X2 = X @ R.T + t
            z1, z2 = X[:, 2], X2[:, 2]
            e1 = ((self._proj(X) - x1) ** 2).sum(1)
            e2 = ((self._proj(X2) - x2) ** 2).sum(1)
            c2 = -R.T @ t
            r1 = X / np.linalg.norm(X, axis=1, keepdims=True).clip(1e-12)
            r2 = (X - c2) / np.linalg.norm(X - c2, axis=1, keepdims=True).clip(1e-12)
            cosp = (r1 * r2).sum(1)
            parallel = cosp >= MIN_COS_PARALLAX
            counted = inl & np.isfinite(X).all(1) & (e1 < 4 * sig2) & (e2 < 4 * sig2) \
                & (parallel | ((z1 > 0) & (z2 > 0)))
            good = counted & ~parallel
            par = np.degrees(np.arccos(np.clip(np.sort(cosp[counted])[min(50, counted.sum() - 1)], -1, 1))) \
                if counted.sum() else 0.0
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R, t
            results.append((int(counted.sum()), int(good.sum()), par, T, X, good))
        if not results:
            return None
        results.sort(key=lambda r: (-r[0], -r[1]))
        best = results[0]
        n_inl = int(inl.sum())
        min_good = max(int(0.9 * n_inl), self.cfg.min_triangulated)
        # ambiguity: among the essential matrix's four motions the same rotation with t and -t
        # reproject every match alike, and only cheirality tells them apart, which parallel rays
        # do not test: compared on the triangulated matches (ORB-SLAM compares the counts, and a
        # forward motion seeing mostly far points is then always ambiguous). A homography's two
        # plane decompositions both explain the matches: compared on the counts (ORB-SLAM's)
        key = 1 if by_triangulated else 0
        similar = sum(1 for r in results if r[key] > 0.7 * best[key])
        if best[0] < min_good or similar > 1 or best[2] < min_parallax \
                or best[1] < self.cfg.min_triangulated:
            return None
        return best[3], best[4], best[5]

    def _proj(self, X):
        z = np.where(np.abs(X[:, 2]) < 1e-12, 1e-12, X[:, 2])
        return np.stack([self.K[0, 0] * X[:, 0] / z + self.K[0, 2], self.K[1, 1] * X[:, 1] / z + self.K[1, 2]], 1)
