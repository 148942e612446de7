"""A frame as the tracker sees it: ORB keypoints, their depth (RGB-D / stereo), colours and a grid.

`SlamFrame.build` turns a `segs.data.frame.Frame` into keypoints plus, per keypoint, a depth and the
virtual right-image coordinate ``ur = u - bf / depth`` (ORB-SLAM's stereo convention; RGB-D uses a
virtual baseline), so that RGB-D and stereo share one code path downstream.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from segs.data.frame import Camera, Frame
from segs.slam.features.extractor import Keypoints, OrbExtractor, to_gray
from segs.slam.geometry import expand_ranges
from segs.slam.features.stereo import StereoMatcher


class KeypointGrid:
    """Bucket keypoints in square cells for vectorized radius queries."""

    def __init__(self, uv: np.ndarray, width: int, height: int, cell: float = 16.0):
        self.cell = float(cell)
        self.nx = int(np.ceil(width / cell)) + 1
        self.ny = int(np.ceil(height / cell)) + 1
        cx = np.clip((uv[:, 0] // cell).astype(np.int64), 0, self.nx - 1)
        cy = np.clip((uv[:, 1] // cell).astype(np.int64), 0, self.ny - 1)
        cid = cy * self.nx + cx
        self.order = np.argsort(cid, kind="stable")
        self.start = np.searchsorted(cid[self.order], np.arange(self.nx * self.ny + 1))
        self.uv = uv

    def query(self, q: np.ndarray, radius: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pairs (query index, keypoint index) with |uv_k - q_i| <= radius_i. q [M,2], radius [M]."""
        if len(q) == 0 or len(self.uv) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        radius = np.broadcast_to(radius, (len(q),))
        x0 = np.clip(((q[:, 0] - radius) // self.cell).astype(np.int64), 0, self.nx - 1)
        x1 = np.clip(((q[:, 0] + radius) // self.cell).astype(np.int64), 0, self.nx - 1)
        y0 = np.clip(((q[:, 1] - radius) // self.cell).astype(np.int64), 0, self.ny - 1)
        y1 = np.clip(((q[:, 1] + radius) // self.cell).astype(np.int64), 0, self.ny - 1)
        qi, row = expand_ranges(y0, y1 - y0 + 1)  # one entry per (query, cell row)
        a = self.start[row * self.nx + x0[qi]]
        b = self.start[row * self.nx + x1[qi] + 1]
        owner, pos = expand_ranges(a, b - a)
        qi = qi[owner]
        ki = self.order[pos]
        dx = self.uv[ki, 0] - q[qi, 0]
        dy = self.uv[ki, 1] - q[qi, 1]
        rq = radius[qi]
        ok = dx * dx + dy * dy <= rq * rq
        return qi[ok], ki[ok]


@dataclass
class SlamFrame:
    """Features of one frame.

    kp: Keypoints (N); depth [N] float64 metres (0: unknown); ur [N] float64 virtual right
    u coordinate (-1: unknown); colors [N,3] float32; points [N] int64 map point per keypoint
    (-1: none); outlier [N] bool; w2c [4,4] or None.
    """

    index: int
    timestamp: float
    kp: Keypoints
    depth: np.ndarray
    ur: np.ndarray
    colors: np.ndarray
    camera: Camera
    bf: float
    grid: KeypointGrid
    points: np.ndarray = field(default=None)  # type: ignore[assignment]
    outlier: np.ndarray = field(default=None)  # type: ignore[assignment]
    w2c: np.ndarray | None = None
    ref_kf: int | None = None
    build_seconds: tuple[float, float] = (0.0, 0.0)  # FrameBuilder.build's (wall, thread CPU) seconds

    def __post_init__(self) -> None:
        n = len(self.kp)
        if self.points is None:
            self.points = np.full(n, -1, np.int64)
        if self.outlier is None:
            self.outlier = np.zeros(n, bool)

    def __len__(self) -> int:
        return len(self.kp)

    @property
    def n_tracked(self) -> int:
        return int(((self.points >= 0) & ~self.outlier).sum())


class FrameBuilder:
    """Builds SlamFrames for one sensor (mono, stereo, rgbd).

    bf: fx * baseline (stereo baseline, or the virtual baseline of RGB-D); max_depth: depths beyond
    it are treated as unknown (for RGB-D noise; stereo points far away are poorly constrained).
    """

    def __init__(self, camera: Camera, sensor: str, extractor: OrbExtractor, bf: float,
                 max_depth: float, stereo: StereoMatcher | None = None, grid_cell: float = 16.0,
                 edge_ratio: float = 0.05):
        self.camera = camera
        self.sensor = sensor
        self.extractor = extractor
        self.bf = float(bf)
        self.max_depth = float(max_depth)
        self.stereo = stereo
        self.grid_cell = grid_cell
        self.edge_ratio = float(edge_ratio)

    def timed_build(self, frame: Frame) -> SlamFrame:
        """build(), with its wall and thread CPU seconds kept on the SlamFrame (build_seconds).
        The builder pickles, so a frame reader in another process can run this."""
        t0, c0 = time.perf_counter(), time.thread_time()
        sf = self.build(frame)
        sf.build_seconds = (time.perf_counter() - t0, time.thread_time() - c0)
        return sf

    def build(self, frame: Frame) -> SlamFrame:
        gray = to_gray(frame.rgb)
        kp = self.extractor.extract(gray)
        n = len(kp)
        depth = np.zeros(n)
        if self.sensor == "rgbd" and frame.depth is not None and n:
            depth = self._lookup_depth(np.asarray(frame.depth, np.float32), kp.uv, self.edge_ratio)
        elif self.sensor == "stereo" and frame.right is not None and self.stereo is not None and n:
            right = self.extractor.extract(to_gray(frame.right))
            depth = self.stereo.match(gray, to_gray(frame.right), kp, right)
        depth[(depth <= 0) | (depth > self.max_depth) | ~np.isfinite(depth)] = 0.0
        ur = np.where(depth > 0, kp.uv[:, 0] - self.bf / np.maximum(depth, 1e-9), -1.0)
        colors = self._colors(frame.rgb, kp.uv)
        grid = KeypointGrid(kp.uv, self.camera.width, self.camera.height, self.grid_cell)
        return SlamFrame(frame.index, float(frame.timestamp), kp, depth, ur, colors, self.camera,
                         self.bf, grid)

    @staticmethod
    def _lookup_depth(depth: np.ndarray, uv: np.ndarray, edge_ratio: float) -> np.ndarray:
        """Depth at the keypoints [N]; 0 where the 3x3 neighbourhood has a hole or a depth edge
        (max - min > edge_ratio * depth): corners often sit on occluding contours."""
        h, w = depth.shape
        x = np.clip(np.rint(uv[:, 0]).astype(np.int64), 0, w - 1)
        y = np.clip(np.rint(uv[:, 1]).astype(np.int64), 0, h - 1)
        d = depth[y, x].astype(np.float64)
        if edge_ratio > 0:  # the 3x3 neighbourhoods inside the image (a 3x3 dilation / erosion's)
            step = np.arange(-1, 2)
            nb = depth[np.clip(y[:, None] + step, 0, h - 1)[:, :, None], np.clip(x[:, None] + step, 0, w - 1)[:, None, :]]
            hi, lo = nb.max(axis=(1, 2)), nb.min(axis=(1, 2))  # [N,3,3] -> [N]
            d[(lo <= 0) | (hi - lo > edge_ratio * d)] = 0.0
        return d

    @staticmethod
    def _colors(rgb: np.ndarray, uv: np.ndarray) -> np.ndarray:
        h, w = rgb.shape[:2]
        x = np.clip(np.rint(uv[:, 0]).astype(np.int64), 0, w - 1)
        y = np.clip(np.rint(uv[:, 1]).astype(np.int64), 0, h - 1)
        c = rgb[y, x]
        if c.ndim == 1:
            c = np.repeat(c[:, None], 3, 1)
        c = c.astype(np.float32)
        if rgb.dtype == np.uint8:
            c /= 255.0
        return np.clip(c, 0.0, 1.0)
