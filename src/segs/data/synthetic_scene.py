"""Procedural textured room for the synthetic sequence: geometry, textures and a ray caster.

World frame: metres, z up, floor at z = 0. The room is an axis-aligned box with a few boxes
inside (furniture, for parallax and occlusion). Every face of every box is a planar surface with
its own procedural texture, precomputed once as a tile of a texture atlas and sampled by the
surface coordinates of the hit point, so colours are a function of the surface point only and
all views are consistent (no lighting, no view dependence).
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

#: Room extent (lo, hi) in metres: 6 x 5 x 3 m.
ROOM = ((-3.0, -2.5, 0.0), (3.0, 2.5, 3.0))
#: Furniture boxes (lo, hi), placed away from the camera paths of synthetic.py.
OBSTACLES = (
    ((-0.35, -0.35, 0.0), (0.35, 0.35, 0.7)),  # low block in the centre
    ((1.9, 1.3, 0.0), (2.7, 2.2, 1.2)),  # cabinet in the +x+y corner
    ((-2.8, -2.2, 0.0), (-2.0, -1.0, 0.9)),  # chest in the -x-y corner
    ((-0.4, 1.9, 0.0), (0.4, 2.5, 2.0)),  # tall shelf against the +y wall
    ((1.0, -2.5, 0.8), (2.0, -2.0, 1.4)),  # wall shelf on the -y wall
)
TEXELS_PER_M = 100.0
_PAD = 2  # replicated border of each atlas tile, so bilinear sampling never bleeds
_ATLAS_WIDTH = 4096
TEXTURES = ("rich", "poor", "mixed")
# In "mixed", these room faces (axis * 2 + side) are texture-poor: the +-x walls and the ceiling.
_MIXED_POOR_FACES = (0, 1, 5)


@dataclass(frozen=True)
class Surface:
    """One planar face: normal along `axis` at coordinate `level`, spanning [lo, hi] on the
    two other axes (b, c) = sorted remaining axes; the texture tile sits at (x0, y0) in the atlas."""

    axis: int
    level: float
    lo: tuple[float, float]
    hi: tuple[float, float]
    x0: int = 0
    y0: int = 0


def _other_axes(axis: int) -> tuple[int, int]:
    return tuple(a for a in range(3) if a != axis)  # type: ignore[return-value]


def _box_faces(lo, hi) -> list[Surface]:
    """6 faces of a box, ordered axis * 2 + side (side 0 = low coordinate, 1 = high)."""
    faces = []
    for axis in range(3):
        b, c = _other_axes(axis)
        for level in (lo[axis], hi[axis]):
            faces.append(Surface(axis, level, (lo[b], lo[c]), (hi[b], hi[c])))
    return faces


def _tile_shape(s: Surface) -> tuple[int, int]:
    """(rows, cols) of the texture tile without padding."""
    cols = max(2, int(np.ceil((s.hi[0] - s.lo[0]) * TEXELS_PER_M)))
    rows = max(2, int(np.ceil((s.hi[1] - s.lo[1]) * TEXELS_PER_M)))
    return rows, cols


def _rich_texture(rng: np.random.Generator, rows: int, cols: int) -> np.ndarray:
    """High-contrast random shapes (discs, quads, triangles, lines) on a random background.

    Returns [rows, cols, 3] float32 in [0.05, 0.95]; about 70 shapes per square metre.
    """
    img = np.empty((rows, cols, 3), np.uint8)
    img[:] = rng.integers(40, 215, 3)
    n = int(70 * rows * cols / TEXELS_PER_M**2) + 4
    colors = rng.integers(13, 243, (n, 3)).tolist()
    sizes = rng.uniform(0.03, 0.25, n) * TEXELS_PER_M
    centres = rng.uniform(0, 1, (n, 2)) * (cols, rows)
    kinds = rng.integers(0, 4, n)
    angles = np.sort(rng.uniform(0, 2 * np.pi, (n, 4)), axis=1)
    radii = sizes[:, None] * rng.uniform(0.4, 0.7, (n, 4))
    widths = rng.integers(2, 6, n).tolist()
    for i in range(n):
        (cx, cy), size, color, kind = centres[i], sizes[i], tuple(colors[i]), kinds[i]
        if kind == 0:
            cv2.circle(img, (int(cx), int(cy)), max(2, int(size / 2)), color, -1, cv2.LINE_AA)
        elif kind in (1, 2):
            ang, rad = angles[i, : 5 - kind], radii[i, : 5 - kind]  # 4 or 3 corners
            pts = np.stack([cx + rad * np.cos(ang), cy + rad * np.sin(ang)], 1)
            cv2.fillPoly(img, [pts.astype(np.int32)], color, cv2.LINE_AA)
        else:
            dx, dy = size * np.cos(angles[i, 0] / 2), size * np.sin(angles[i, 0] / 2)
            p0, p1 = (int(cx - dx), int(cy - dy)), (int(cx + dx), int(cy + dy))
            cv2.line(img, p0, p1, color, widths[i], cv2.LINE_AA)
    out = cv2.GaussianBlur(img.astype(np.float32) / 255.0, (0, 0), 0.6)
    return np.clip(out, 0.05, 0.95)


def _poor_texture(rng: np.random.Generator, rows: int, cols: int) -> np.ndarray:
    """Smooth, low-contrast shading (+-3 %) around a pale base colour: [rows, cols, 3] float32."""
    base = rng.uniform(0.45, 0.75, 3).astype(np.float32)
    coarse = rng.normal(0.0, 1.0, (4, 4, 1)).astype(np.float32)
    smooth = cv2.resize(coarse, (cols, rows), interpolation=cv2.INTER_CUBIC)
    smooth = smooth.reshape(rows, cols, 1)
    return np.clip(base * (1.0 + 0.03 * smooth), 0.05, 0.95).astype(np.float32)


def _pack(surfaces: list[Surface]) -> tuple[list[Surface], tuple[int, int]]:
    """Shelf-pack the padded tiles into an atlas; returns surfaces with x0, y0 and atlas shape."""
    order = sorted(range(len(surfaces)), key=lambda i: -_tile_shape(surfaces[i])[0])
    placed: list[Surface | None] = [None] * len(surfaces)
    x = y = shelf = 0
    for i in order:
        rows, cols = (v + 2 * _PAD for v in _tile_shape(surfaces[i]))
        if x + cols > _ATLAS_WIDTH:
            x, y, shelf = 0, y + shelf, 0
        s = surfaces[i]
        placed[i] = Surface(s.axis, s.level, s.lo, s.hi, x, y)
        x, shelf = x + cols, max(shelf, rows)
    return placed, (y + shelf, _ATLAS_WIDTH)  # type: ignore[return-value]


class Scene:
    """The room, its furniture and the 8-bit texture atlas for one (texture, seed).

    Use :func:`get_scene` (cached) rather than the constructor.
    """

    def __init__(self, texture: str = "rich", seed: int = 0):
        faces = _box_faces(*ROOM)
        for lo, hi in OBSTACLES:
            faces += _box_faces(lo, hi)
        self.surfaces, shape = _pack(faces)
        self.atlas = np.zeros(shape + (3,), np.uint8)  # 8 bit: 4x less memory, faster remap
        rng = np.random.default_rng(seed)
        for sid, s in enumerate(self.surfaces):
            poor = texture == "poor" or (texture == "mixed" and sid in _MIXED_POOR_FACES)
            rows, cols = _tile_shape(s)
            tile = (_poor_texture if poor else _rich_texture)(rng, rows, cols)
            tile = cv2.copyMakeBorder(tile, _PAD, _PAD, _PAD, _PAD, cv2.BORDER_REPLICATE)
            tile = np.round(tile * 255).astype(np.uint8)
            self.atlas[s.y0 : s.y0 + rows + 2 * _PAD, s.x0 : s.x0 + cols + 2 * _PAD] = tile
        self._tables()

    def _tables(self) -> None:
        """Per-surface lookup arrays used by :meth:`shade`."""
        s = self.surfaces
        self._axis = np.array([f.axis for f in s])
        self._lo = np.array([f.lo for f in s], np.float32)
        self._max = np.array([np.array(_tile_shape(f)[::-1]) - 1 for f in s], np.float32)
        self._off = np.array([(f.x0 + _PAD, f.y0 + _PAD) for f in s], np.float32)
        self._boxes = np.array(OBSTACLES, np.float32)  # [K, 2, 3]

    def cast(self, origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nearest hit of rays origin + t * dirs.

        origin: [3] (inside the room, outside the furniture); dirs: [3,N] (not normalised,
        component-major for speed). Returns t [N] float32 (in units of |dirs|) and surface id [N].
        """
        o = np.asarray(origin, np.float32)
        d = [np.where(np.abs(c) < 1e-9, np.float32(1e-9), c).astype(np.float32) for c in dirs]
        inv = [1.0 / c for c in d]
        lo, hi = ROOM
        ta = [np.where(d[a] > 0, (hi[a] - o[a]) * inv[a], (lo[a] - o[a]) * inv[a]) for a in range(3)]
        t = np.minimum(np.minimum(ta[0], ta[1]), ta[2])
        sid = np.where(t == ta[0], d[0] > 0, np.where(t == ta[1], 2 + (d[1] > 0), 4 + (d[2] > 0)))
        for k, (blo, bhi) in enumerate(self._boxes):
            t1 = [(blo[a] - o[a]) * inv[a] for a in range(3)]
            t2 = [(bhi[a] - o[a]) * inv[a] for a in range(3)]
            tmin = [np.minimum(t1[a], t2[a]) for a in range(3)]
            near = np.maximum(np.maximum(tmin[0], tmin[1]), tmin[2])
            far = np.minimum(np.minimum(np.maximum(t1[0], t2[0]), np.maximum(t1[1], t2[1])),
                             np.maximum(t1[2], t2[2]))
            hit = (near <= far) & (near > 1e-6) & (near < t)
            if hit.any():
                axis = np.where(near == tmin[0], 0, np.where(near == tmin[1], 1, 2))[hit]
                side = np.stack(d)[axis, np.flatnonzero(hit)] < 0
                t[hit] = near[hit]
                sid[hit] = 6 + 6 * k + axis * 2 + side
        return t, sid

    def shade(self, points: list[np.ndarray], sid: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        """Texture colour of surface points (3 arrays [N], x y z) on surfaces sid [N] -> [H,W,3]."""
        axis = self._axis[sid]
        pb = np.where(axis == 0, points[1], points[0])
        pc = np.where(axis == 2, points[1], points[2])
        mx = (pb - self._lo[sid, 0]) * TEXELS_PER_M - 0.5
        my = (pc - self._lo[sid, 1]) * TEXELS_PER_M - 0.5
        mx = np.clip(mx, 0.0, self._max[sid, 0]) + self._off[sid, 0]
        my = np.clip(my, 0.0, self._max[sid, 1]) + self._off[sid, 1]
        mx, my = (m.reshape(shape).astype(np.float32) for m in (mx, my))
        rgb = cv2.remap(self.atlas, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        return rgb.astype(np.float32) * np.float32(1 / 255)


@lru_cache(maxsize=4)
def get_scene(texture: str = "rich", seed: int = 0) -> Scene:
    """Shared, cached :class:`Scene` (texture generation takes a few tens of milliseconds)."""
    return Scene(texture, seed)
