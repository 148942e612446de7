"""Procedural textured scenes for the synthetic sequence: geometry, textures and a ray caster.

World frame: metres, z up, floor at z = 0. A scene (layout) is an axis-aligned box (the room, or a
long corridor) with a few boxes inside (furniture, pillars: parallax and occlusion). Every face of
every box is a planar surface with its own procedural texture, precomputed once as a tile of a
texture atlas and sampled by the surface coordinates of the hit point, so colours are a function
of the surface point only and all views are consistent (no lighting, no view dependence).

Layouts: "room" (6 x 5 x 3 m, the default) and "corridor" (5 m wide, 3.5 m high, 80 m long, with
pillars and low blocks along its walls: a street-like depth range from 1 m to 70 m). The
corridor's texture is mip-mapped (distant walls would otherwise alias into unstable corners).
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
#: Corridor extent: 5 m wide (x), 80 m long (y, the camera travels along +y), 3.5 m high.
CORRIDOR = ((-2.5, -4.0, 0.0), (2.5, 76.0, 3.5))


def _corridor_obstacles() -> tuple:
    """Pillars (0.5 x 0.6 m, full height) every 9 m alternating sides, and low blocks (1 m deep,
    2 m long, 0.9 m high) on the other side 3 m further: depth steps along both walls."""
    out = []
    for k in range(8):
        y0, side = 2.0 + 9.0 * k, 1.0 if k % 2 else -1.0
        px = (2.0, 2.5) if side > 0 else (-2.5, -2.0)
        out.append(((px[0], y0, 0.0), (px[1], y0 + 0.6, 3.5)))
        bx = (-2.5, -1.5) if side > 0 else (1.5, 2.5)
        out.append(((bx[0], y0 + 3.0, 0.0), (bx[1], y0 + 5.0, 0.9)))
    return tuple(out)


CORRIDOR_OBSTACLES = _corridor_obstacles()
#: layout -> (bounding box, obstacles, mip levels of the texture)
LAYOUTS = {"room": (ROOM, OBSTACLES, 1), "corridor": (CORRIDOR, CORRIDOR_OBSTACLES, 4)}
TEXELS_PER_M = 100.0
_PAD = 2  # replicated border of each atlas tile, so bilinear sampling never bleeds
_ATLAS_WIDTH = 4096
TEXTURES = ("rich", "poor", "mixed")
# In "mixed", these room faces (axis * 2 + side) are texture-poor: the +-x walls and the ceiling.
_MIXED_POOR_FACES = (0, 1, 5)


@dataclass(frozen=True)
class Surface:
    """One planar face: normal along `axis` at coordinate `level`, spanning [lo, hi] on the
    two other axes (b, c) = sorted remaining axes; the texture tile sits at (x0, y0) in the atlas,
    with b along its columns and c along its rows, or the other way round when `transposed`
    (tiles much taller than wide, e.g. a corridor floor, are stored lying down)."""

    axis: int
    level: float
    lo: tuple[float, float]
    hi: tuple[float, float]
    x0: int = 0
    y0: int = 0
    transposed: bool = False


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


def _tile_shape(s: Surface, texels_per_m: float = TEXELS_PER_M) -> tuple[int, int]:
    """(rows, cols) of the texture tile without padding (c along rows, b along columns)."""
    cols = max(2, int(np.ceil((s.hi[0] - s.lo[0]) * texels_per_m)))
    rows = max(2, int(np.ceil((s.hi[1] - s.lo[1]) * texels_per_m)))
    return rows, cols


def _stored_shape(s: Surface, texels_per_m: float) -> tuple[int, int]:
    """(rows, cols) of the tile as stored in the atlas (lying down when transposed)."""
    rows, cols = _tile_shape(s, texels_per_m)
    return (cols, rows) if s.transposed else (rows, cols)


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


def _pack(surfaces: list[Surface], pad: int = _PAD,
          texels_per_m: float = TEXELS_PER_M) -> tuple[list[Surface], tuple[int, int]]:
    """Shelf-pack the padded tiles into an atlas; returns surfaces with x0, y0 and atlas shape.

    Tiles taller than half the atlas width are stored lying down (transposed). The atlas is
    _ATLAS_WIDTH wide, or as wide as the widest tile (long corridor walls)."""
    surfaces = [Surface(f.axis, f.level, f.lo, f.hi, transposed=_tile_shape(f, texels_per_m)[0] > _ATLAS_WIDTH // 2)
                for f in surfaces]
    shapes = [_stored_shape(f, texels_per_m) for f in surfaces]
    order = sorted(range(len(surfaces)), key=lambda i: -shapes[i][0])
    placed: list[Surface | None] = [None] * len(surfaces)
    width = max([_ATLAS_WIDTH] + [c + 2 * pad for _, c in shapes])
    x = y = shelf = 0
    for i in order:
        rows, cols = (v + 2 * pad for v in shapes[i])
        if x + cols > width:
            x, y, shelf = 0, y + shelf, 0
        s = surfaces[i]
        placed[i] = Surface(s.axis, s.level, s.lo, s.hi, x, y, s.transposed)
        x, shelf = x + cols, max(shelf, rows)
    return placed, (y + shelf, width)  # type: ignore[return-value]


class Scene:
    """One layout (see LAYOUTS), its boxes and the 8-bit texture atlas for one (texture, seed).

    Use :func:`get_scene` (cached) rather than the constructor. `mip_levels` > 1: the atlas has
    a pyramid of that many levels (each half the previous, area-averaged) and :meth:`shade`
    samples it trilinearly by the pixel footprint on the surface (see :meth:`footprint`).
    """

    def __init__(self, texture: str = "rich", seed: int = 0, layout: str = "room"):
        self.bounds, obstacles, self.mip_levels = LAYOUTS[layout]
        # the room keeps its historical texel density and padding; the corridor has 2x coarser
        # texels (its shapes are 6-50 cm) and pads for its mip levels
        self.texels_per_m = TEXELS_PER_M if layout == "room" else TEXELS_PER_M / 2
        self.pad = _PAD * 2 ** (self.mip_levels - 1)
        faces = _box_faces(*self.bounds)
        for lo, hi in obstacles:
            faces += _box_faces(lo, hi)
        self.surfaces, shape = _pack(faces, self.pad, self.texels_per_m)
        if self.mip_levels > 1:  # every level an exact halving
            m = 2 ** (self.mip_levels - 1)
            shape = (-(-shape[0] // m) * m, -(-shape[1] // m) * m)
        self.atlas = np.zeros(shape + (3,), np.uint8)  # 8 bit: 4x less memory, faster remap
        rng = np.random.default_rng(seed)
        pad = self.pad
        for sid, s in enumerate(self.surfaces):
            poor = texture == "poor" or (texture == "mixed" and sid in _MIXED_POOR_FACES)
            rows, cols = _tile_shape(s, self.texels_per_m)
            tile = (_poor_texture if poor else _rich_texture)(rng, rows, cols)
            if s.transposed:
                tile, (rows, cols) = np.ascontiguousarray(tile.transpose(1, 0, 2)), (cols, rows)
            tile = cv2.copyMakeBorder(tile, pad, pad, pad, pad, cv2.BORDER_REPLICATE)
            tile = np.round(tile * 255).astype(np.uint8)
            self.atlas[s.y0 : s.y0 + rows + 2 * pad, s.x0 : s.x0 + cols + 2 * pad] = tile
        self.mips = [self.atlas]
        for _ in range(1, self.mip_levels):
            a = self.mips[-1]
            self.mips.append(cv2.resize(a, (a.shape[1] // 2, a.shape[0] // 2), interpolation=cv2.INTER_AREA))
        self._tables(obstacles)

    def _tables(self, obstacles) -> None:
        """Per-surface lookup arrays used by :meth:`shade`."""
        s = self.surfaces
        self._axis = np.array([f.axis for f in s])
        self._lo = np.array([f.lo for f in s], np.float32)
        self._max = np.array([np.array(_tile_shape(f, self.texels_per_m)[::-1]) - 1 for f in s], np.float32)
        self._off = np.array([(f.x0 + self.pad, f.y0 + self.pad) for f in s], np.float32)
        self._transposed = np.array([f.transposed for f in s])
        self._boxes = np.array(obstacles, np.float32)  # [K, 2, 3]

    def cast(self, origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nearest hit of rays origin + t * dirs.

        origin: [3] (inside the bounds, outside the boxes); dirs: [3,N] (not normalised,
        component-major for speed). Returns t [N] float32 (in units of |dirs|) and surface id [N].
        Boxes wholly behind every ray (behind the plane through the origin normal to the mean
        ray, when all rays point to its front side) are skipped: they cannot be hit.
        """
        o = np.asarray(origin, np.float32)
        d = [np.where(np.abs(c) < 1e-9, np.float32(1e-9), c).astype(np.float32) for c in dirs]
        inv = [1.0 / c for c in d]
        lo, hi = self.bounds
        ta = [np.where(d[a] > 0, (hi[a] - o[a]) * inv[a], (lo[a] - o[a]) * inv[a]) for a in range(3)]
        t = np.minimum(np.minimum(ta[0], ta[1]), ta[2])
        sid = np.where(t == ta[0], d[0] > 0, np.where(t == ta[1], 2 + (d[1] > 0), 4 + (d[2] > 0)))
        for k in self._boxes_in_front(o, d):
            blo, bhi = self._boxes[k]
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

    def _boxes_in_front(self, o: np.ndarray, d: list[np.ndarray]) -> list[int]:
        """Indices of the boxes that rays d (3 arrays [N]) from o may hit (see :meth:`cast`)."""
        axis = np.array([float(c.mean()) for c in d], np.float32)
        if (d[0] * axis[0] + d[1] * axis[1] + d[2] * axis[2]).min() <= 0:
            return list(range(len(self._boxes)))
        corners = self._boxes[:, [0, 1], :]  # [K,2,3] lo / hi
        cx, cy, cz = np.meshgrid([0, 1], [0, 1], [0, 1], indexing="ij")
        pts = np.stack([corners[:, cx.ravel(), 0], corners[:, cy.ravel(), 1], corners[:, cz.ravel(), 2]], -1)
        front = ((pts - o) @ axis > 0).any(1)  # [K]
        return np.flatnonzero(front).tolist()

    def footprint(self, dirs: list[np.ndarray], t: np.ndarray, sid: np.ndarray, fx: float) -> np.ndarray:
        """Pixel footprint [N] in texels on the hit surface: ray length / fx, stretched by the
        incidence (geometric mean of the two axes, 1 / sqrt(cos), at most x4)."""
        norm = np.sqrt(dirs[0] ** 2 + dirs[1] ** 2 + dirs[2] ** 2)
        axis = self._axis[sid]
        cos = np.abs(np.where(axis == 0, dirs[0], np.where(axis == 1, dirs[1], dirs[2]))) / norm
        stretch = 1.0 / np.sqrt(np.maximum(cos, 1.0 / 16))
        return t * norm / fx * self.texels_per_m * stretch

    def shade(self, points: list[np.ndarray], sid: np.ndarray, shape: tuple[int, int],
              footprint: np.ndarray | None = None) -> np.ndarray:
        """Texture colour of surface points (3 arrays [N], x y z) on surfaces sid [N] -> [H,W,3].

        footprint: [N] texels per pixel (:meth:`footprint`) for the mip levels; None or a single
        level: bilinear samples of the full-resolution atlas."""
        axis = self._axis[sid]
        pb = np.where(axis == 0, points[1], points[0])
        pc = np.where(axis == 2, points[1], points[2])
        mx = (pb - self._lo[sid, 0]) * self.texels_per_m - 0.5
        my = (pc - self._lo[sid, 1]) * self.texels_per_m - 0.5
        mx = np.clip(mx, 0.0, self._max[sid, 0])
        my = np.clip(my, 0.0, self._max[sid, 1])
        tr = self._transposed[sid]
        if tr.any():
            mx, my = np.where(tr, my, mx), np.where(tr, mx, my)
        mx = mx + self._off[sid, 0]
        my = my + self._off[sid, 1]
        if footprint is None or self.mip_levels == 1:
            mx, my = (m.reshape(shape).astype(np.float32) for m in (mx, my))
            rgb = cv2.remap(self.atlas, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            return rgb.astype(np.float32) * np.float32(1 / 255)
        return self._shade_mip(mx, my, footprint).reshape(shape + (3,))

    def _shade_mip(self, mx: np.ndarray, my: np.ndarray, footprint: np.ndarray) -> np.ndarray:
        """Trilinear sampling of the mip pyramid at level-0 texel coordinates mx, my [N] -> [N,3]."""
        lvl = np.clip(np.log2(np.maximum(footprint, 1e-6)), 0.0, self.mip_levels - 1)
        out = np.zeros((len(mx), 3), np.float32)
        for k, img in enumerate(self.mips):
            w = np.maximum(0.0, 1.0 - np.abs(lvl - k))
            sel = np.flatnonzero(w > 0)
            if len(sel) == 0:
                continue
            f, n = 0.5 ** k, len(sel)
            rows = -(-n // 1024)  # remap wants maps below 32767 rows: 1024 wide blocks
            ux, uy = (np.zeros(rows * 1024, np.float32) for _ in range(2))
            ux[:n] = (mx[sel] + 0.5) * f - 0.5
            uy[:n] = (my[sel] + 0.5) * f - 0.5
            c = cv2.remap(img, ux.reshape(rows, 1024), uy.reshape(rows, 1024), cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_REPLICATE).reshape(-1, 3)[:n]
            out[sel] += w[sel, None].astype(np.float32) * c.astype(np.float32)
        return out * np.float32(1 / 255)


@lru_cache(maxsize=4)
def get_scene(texture: str = "rich", seed: int = 0, layout: str = "room") -> Scene:
    """Shared, cached :class:`Scene` (texture generation takes a few tens of milliseconds for
    the room, about a second for the corridor)."""
    return Scene(texture, seed, layout)
