"""Sparse stereo matching on rectified pairs (ORB-SLAM's ComputeStereoMatches, vectorized).

For each left keypoint: right keypoints within +-2 scale rows, on a neighbouring octave, with a
disparity in [0, bf / min_depth]; the best Hamming distance below a threshold; then a sub-pixel
refinement by sum of absolute differences of an 11x11 patch at the keypoint's pyramid level over
+-5 level pixels with a parabola fit; finally matches whose SAD is far above the median are dropped.
"""
from __future__ import annotations

import cv2
import numpy as np

from segs.slam.features.extractor import Keypoints, hamming_pairs
from segs.slam.geometry import expand_ranges


class StereoMatcher:
    """bf: fx * baseline; scales [L] pyramid scale per octave; max_hamming: descriptor threshold."""

    def __init__(self, bf: float, scales: np.ndarray, max_hamming: int = 75, min_depth: float = 0.0,
                 window: int = 5, search: int = 5):
        self.bf = float(bf)
        self.scales = np.asarray(scales, np.float64)
        self.max_hamming = int(max_hamming)
        self.max_disp = self.bf / min_depth if min_depth > 0 else np.inf
        self.w = int(window)
        self.s = int(search)

    def match(self, gray_l: np.ndarray, gray_r: np.ndarray, kl: Keypoints, kr: Keypoints) -> np.ndarray:
        """Depth [N] (0 where unmatched) of the left keypoints kl."""
        depth = np.zeros(len(kl))
        if len(kl) == 0 or len(kr) == 0:
            return depth
        li, ri = self._candidates(kl, kr)
        if len(li) == 0:
            return depth
        d = hamming_pairs(kl.desc, li, kr.desc, ri)
        ok = d < self.max_hamming
        li, ri, d = li[ok], ri[ok], d[ok]
        order = np.lexsort((d, li))
        li, ri = li[order], ri[order]
        first = np.r_[True, li[1:] != li[:-1]]
        li, ri = li[first], ri[first]
        ur, sad = self._refine(gray_l, gray_r, kl, li, kr.uv[ri, 0])
        good = np.isfinite(ur)
        if good.any():
            med = np.median(sad[good])
            good &= sad <= 1.5 * 1.4 * med
        disp = kl.uv[li, 0] - ur
        good &= (disp > 0.01) & (disp < self.max_disp)
        depth[li[good]] = self.bf / disp[good]
        return depth

    def _candidates(self, kl: Keypoints, kr: Keypoints) -> tuple[np.ndarray, np.ndarray]:
        order = np.argsort(kr.uv[:, 1], kind="stable")
        vr = kr.uv[order, 1]
        r = 2.0 * self.scales[kl.octave]
        a = np.searchsorted(vr, kl.uv[:, 1] - r, "left")
        b = np.searchsorted(vr, kl.uv[:, 1] + r, "right")
        li, pos = expand_ranges(a, b - a)
        ri = order[pos]
        disp = kl.uv[li, 0] - kr.uv[ri, 0]
        ok = (disp >= 0) & (disp <= min(self.max_disp, 1e9)) & (np.abs(kr.octave[ri] - kl.octave[li]) <= 1)
        return li[ok], ri[ok]

    def _refine(self, gl: np.ndarray, gr: np.ndarray, kl: Keypoints, li: np.ndarray,
                ur0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Sub-pixel right u per match (NaN where the refinement fails) and its SAD."""
        w, s = self.w, self.s
        ur = np.full(len(li), np.nan)
        sad_best = np.full(len(li), np.inf)
        offs = np.arange(-w, w + 1)
        for lvl in np.unique(kl.octave[li]):
            m = np.flatnonzero(kl.octave[li] == lvl)
            sc = self.scales[lvl]
            size = (int(round(gl.shape[1] / sc)), int(round(gl.shape[0] / sc)))
            il = cv2.resize(gl, size, interpolation=cv2.INTER_LINEAR).astype(np.float32)
            ir = cv2.resize(gr, size, interpolation=cv2.INTER_LINEAR).astype(np.float32)
            H, W = il.shape
            ul = np.rint(kl.uv[li[m], 0] / sc).astype(np.int64)
            vl = np.rint(kl.uv[li[m], 1] / sc).astype(np.int64)
            u_r = np.rint(ur0[m] / sc).astype(np.int64)
            inside = (vl - w >= 0) & (vl + w < H) & (ul - w >= 0) & (ul + w < W) \
                & (u_r - w - s >= 0) & (u_r + w + s < W)
            m, ul, vl, u_r = m[inside], ul[inside], vl[inside], u_r[inside]
            if len(m) == 0:
                continue
            rows = vl[:, None, None] + offs[None, :, None]
            pl = il[rows, ul[:, None, None] + offs[None, None, :]]  # [M,2w+1,2w+1]
            pl = pl - pl[:, w:w + 1, w:w + 1]
            cols = u_r[:, None, None] + np.arange(-w - s, w + s + 1)[None, None, :]
            strip = ir[rows, cols]  # [M,2w+1,2w+1+2s]
            sad = np.stack([np.abs(pl - (strip[:, :, k:k + 2 * w + 1] - strip[:, w:w + 1, k + w:k + w + 1])).sum((1, 2))
                            for k in range(2 * s + 1)], 1)  # [M,2s+1]
            best = sad.argmin(1)
            ok = (best > 0) & (best < 2 * s)
            r = np.arange(len(m))
            b1 = np.clip(best, 1, 2 * s - 1)
            d1, d2, d3 = sad[r, b1 - 1], sad[r, b1], sad[r, b1 + 1]
            den = 2.0 * (d1 + d3 - 2.0 * d2)
            delta = np.where(np.abs(den) > 1e-9, (d1 - d3) / np.where(den == 0, 1, den), 0.0)
            ok &= np.abs(delta) <= 1.0
            val = sc * (u_r + (best - s) + delta)
            ur[m[ok]] = val[ok]
            sad_best[m[ok]] = d2[ok]
        return ur, sad_best
