"""ORB extraction with a scale pyramid and an even spatial distribution, and binary-descriptor helpers.

OpenCV's ORB builds the pyramid, runs FAST (with a low threshold), ranks by Harris score, computes
the orientation and the rBRIEF descriptors. It over-samples (``oversample`` x the wanted count); the
even distribution is then imposed in numpy, ORB-SLAM's grid idea: on every pyramid level the image
is cut in cells of ``cell_size`` level pixels and keypoints are taken round-robin over the cells,
best response first (all cells' best, then all cells' second best, ...), up to the level's quota
(ORB-SLAM's geometric split of the features over the levels). Weak corners thus survive only where
nothing stronger exists nearby, which is what ORB-SLAM's lowered-FAST-threshold fallback per cell
achieves.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass
class Keypoints:
    """Keypoints of one image (level-0 pixel coordinates).

    uv:       [N,2] float64 pixel position
    octave:   [N] int64 pyramid level
    angle:    [N] float32 orientation in degrees
    response: [N] float32 detector score
    desc:     [N,32] uint8 rBRIEF descriptors (C-contiguous)
    """

    uv: np.ndarray
    octave: np.ndarray
    angle: np.ndarray
    response: np.ndarray
    desc: np.ndarray

    def __len__(self) -> int:
        return len(self.uv)

    def subset(self, idx: np.ndarray) -> "Keypoints":
        return Keypoints(self.uv[idx], self.octave[idx], self.angle[idx], self.response[idx],
                         np.ascontiguousarray(self.desc[idx]))


def empty_keypoints() -> Keypoints:
    return Keypoints(np.zeros((0, 2)), np.zeros(0, np.int64), np.zeros(0, np.float32),
                     np.zeros(0, np.float32), np.zeros((0, 32), np.uint8))


def hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamming distances of binary descriptors a [...,32] uint8 vs b [...,32] uint8 (broadcast) -> int."""
    a64 = np.ascontiguousarray(a).view(np.uint64)
    b64 = np.ascontiguousarray(b).view(np.uint64)
    return np.bitwise_count(a64 ^ b64).sum(-1, dtype=np.int64)


def hamming_pairs(da: np.ndarray, ia: np.ndarray, db: np.ndarray, ib: np.ndarray) -> np.ndarray:
    """Hamming distance between da[ia[k]] and db[ib[k]] for each pair k -> [K] int64."""
    a64 = np.ascontiguousarray(da).view(np.uint64)
    b64 = np.ascontiguousarray(db).view(np.uint64)
    return np.bitwise_count(a64[ia] ^ b64[ib]).sum(-1, dtype=np.int64)


def hamming_matrix(da: np.ndarray, db: np.ndarray) -> np.ndarray:
    """All-pairs Hamming distances [A,32] x [B,32] -> [A,B] int64 (moderate sizes only)."""
    a64 = np.ascontiguousarray(da).view(np.uint64)
    b64 = np.ascontiguousarray(db).view(np.uint64)
    out = np.zeros((len(a64), len(b64)), np.int64)
    for w in range(4):  # word by word keeps the temporary at [A,B]
        out += np.bitwise_count(a64[:, w, None] ^ b64[None, :, w])
    return out


def level_quotas(n_features: int, scale_factor: float, n_levels: int) -> np.ndarray:
    """ORB-SLAM's features per pyramid level: geometric in the level's area scale -> [L] int64."""
    inv = 1.0 / scale_factor
    first = n_features * (1 - inv) / (1 - inv ** n_levels) if n_levels > 1 else n_features
    q = np.round(first * inv ** np.arange(n_levels)).astype(np.int64)
    q[-1] = max(n_features - q[:-1].sum(), 0)
    return q


def round_robin_select(cells: np.ndarray, response: np.ndarray, quota: int) -> np.ndarray:
    """Indices of up to `quota` items, best responses first per cell, one cell round at a time."""
    if len(cells) <= quota:
        return np.arange(len(cells))
    order = np.lexsort((-response, cells))
    sc = cells[order]
    start = np.r_[0, np.flatnonzero(sc[1:] != sc[:-1]) + 1]
    rank = np.arange(len(sc)) - np.repeat(start, np.diff(np.r_[start, len(sc)]))
    pick = np.lexsort((-response[order], rank))[:quota]
    return order[pick]


class OrbExtractor:
    """ORB features with pyramid and even distribution.

    n_features: wanted keypoints per image; scale_factor / n_levels: pyramid; fast_threshold: FAST
    threshold of the first pass; min_fast_threshold: threshold of a second pass run when the first
    finds fewer than n_features corners (texture-poor images); floor_fast_threshold: a third pass
    when the second still finds fewer (blurred or heavily compressed texture-poor frames; not below
    min_fast_threshold: none); cell_size: distribution cell in level pixels; oversample: candidates
    kept by OpenCV before the distribution (x n_features).
    """

    def __init__(self, n_features: int = 1500, scale_factor: float = 1.2, n_levels: int = 8,
                 fast_threshold: int = 20, min_fast_threshold: int = 7, cell_size: int = 30,
                 oversample: float = 3.0, floor_fast_threshold: int = 3):
        self._args = (n_features, scale_factor, n_levels, fast_threshold, min_fast_threshold, cell_size,
                      oversample, floor_fast_threshold)
        self.n_features = int(n_features)
        self.scale_factor = float(scale_factor)
        self.n_levels = int(n_levels)
        self.cell_size = float(cell_size)
        self.quotas = level_quotas(self.n_features, self.scale_factor, self.n_levels)
        n_cand = int(self.n_features * oversample)
        make = lambda th: cv2.ORB_create(nfeatures=n_cand, scaleFactor=self.scale_factor,
                                         nlevels=self.n_levels, edgeThreshold=19, patchSize=31,
                                         fastThreshold=int(th), scoreType=cv2.ORB_HARRIS_SCORE)
        # FAST thresholds tried in turn until one finds n_features corners (the last one's are kept)
        ths = [int(fast_threshold)]
        for th in (min_fast_threshold, floor_fast_threshold):
            if int(th) < ths[-1]:
                ths.append(int(th))
        self.fast_thresholds = tuple(ths)
        self._orbs = [make(th) for th in ths]
        self.scales = self.scale_factor ** np.arange(self.n_levels)
        self.sigma2 = self.scales ** 2

    def __reduce__(self):
        """Pickled as its arguments (OpenCV's ORB objects do not pickle): a frame reader in another
        process builds the same extractor."""
        return OrbExtractor, self._args

    @classmethod
    def from_config(cls, fc) -> "OrbExtractor":
        """The extractor of a FeatureConfig (segs.slam.config; conf/slam/orb.yaml `features`)."""
        return cls(fc.n_features, fc.scale_factor, fc.n_levels, fc.fast_threshold, fc.min_fast_threshold,
                   fc.cell_size, fc.oversample, fc.floor_fast_threshold)

    def _detect(self, gray: np.ndarray) -> list:
        """Corners (no descriptors) of the first FAST threshold that finds n_features (else the last's)."""
        for orb in self._orbs:
            kps = orb.detect(gray, None)
            if len(kps) >= self.n_features:
                break
        return kps

    def extract(self, gray: np.ndarray) -> Keypoints:
        """gray [H,W] uint8 -> evenly distributed Keypoints (at most n_features).

        Descriptors are computed for the distributed keypoints only (a third of the candidates;
        the same bytes as computing them for all, since each depends on its own patch alone)."""
        kps = self._detect(gray)
        if not kps:
            return empty_keypoints()
        uv, octave, resp = _keypoint_arrays(kps, angle=False)
        keep = self._distribute(uv, octave, resp)
        kps, desc = self._orbs[0].compute(gray, [kps[i] for i in keep.tolist()])
        if not kps or desc is None:
            return empty_keypoints()
        uv, octave, angle, resp = _keypoint_arrays(kps)
        return Keypoints(uv, octave, angle, resp, np.ascontiguousarray(desc))

    def _distribute(self, uv: np.ndarray, octave: np.ndarray, resp: np.ndarray) -> np.ndarray:
        """Even spatial selection per level (quota per level; leftovers fill the total) -> indices."""
        cell = self.cell_size * self.scales[octave]
        cx = np.floor(uv[:, 0] / cell).astype(np.int64)
        cy = np.floor(uv[:, 1] / cell).astype(np.int64)
        cells = (octave * 4096 + cy) * 4096 + cx
        chosen = []
        for lvl in range(self.n_levels):
            idx = np.flatnonzero(octave == lvl)
            if len(idx):
                chosen.append(idx[round_robin_select(cells[idx], resp[idx], int(self.quotas[lvl]))])
        sel = np.concatenate(chosen) if chosen else np.zeros(0, np.int64)
        missing = self.n_features - len(sel)
        if missing > 0 and len(sel) < len(uv):
            rest = np.setdiff1d(np.arange(len(uv)), sel)
            sel = np.concatenate([sel, rest[round_robin_select(cells[rest], resp[rest], missing)]])
        return np.sort(sel)


def _keypoint_arrays(kps: list, angle: bool = True) -> tuple[np.ndarray, ...]:
    """OpenCV keypoints -> (uv [N,2] float64, octave [N] int64, angle [N] float32 (left out when
    not angle), response [N] float32): one C++ conversion for the positions, generators into
    arrays for the rest (Python attribute reads, under the interpreter lock: only those needed)."""
    n = len(kps)
    uv, octave = cv2.KeyPoint_convert(kps).astype(np.float64), np.fromiter((k.octave for k in kps), np.int64, n)
    resp = np.fromiter((k.response for k in kps), np.float32, n)
    if not angle:
        return uv, octave, resp
    return uv, octave, np.fromiter((k.angle for k in kps), np.float32, n), resp


def to_gray(rgb: np.ndarray) -> np.ndarray:
    """[H,W,3] float in [0,1] (or uint8) -> [H,W] uint8 grey."""
    if rgb.dtype != np.uint8:  # x 255, rounded, saturated to [0, 255] (OpenCV: 7x numpy's clip),
        # as one channel so that the scalar multiplies every value in every OpenCV version
        flat = np.ascontiguousarray(rgb, np.float32).reshape(rgb.shape[0], -1)
        rgb = cv2.multiply(flat, 255.0, dtype=cv2.CV_8U).reshape(rgb.shape)
    if rgb.ndim == 2:
        return rgb
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
