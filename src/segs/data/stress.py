"""Stress generators for the stability suite: any sequence, degraded deterministically by a level.

``apply_stress(sequence, kind, level, seed=0, **options)`` returns a :class:`StressedSequence`
that wraps the sequence (config: ``data.stress={kind: noise, level: 8}``). Level 0 is the
identity for every kind (the same frames, bit for bit); larger levels degrade more. The same
(seed, kind, level, options) always gives the same frames, whatever order they are read in.

Kinds, their level and options (defaults in brackets):

- ``exposure``: a sudden gain / white-balance step. From frame ``round(at * N)`` on, every
  colour image is multiplied per channel by ``2 ** (s * level + wb * level * [1, 0, -1])`` and
  clipped to [0, 1]; level = gain step in stops (EV). Options: ``at`` [0.5] (fraction of the
  sequence where the step happens), ``direction`` ["down"] ("down" darker, "up" brighter and
  soon saturated; s = -1 / +1),
  ``wb`` [0.25] (white-balance shift in stops per stop of gain: red up, blue down).
- ``motion_blur``: a linear blur kernel (anti-aliased line, normalised) of length
  ``level / 100 * width`` pixels, i.e. level = blur length in percent of the image width.
  Options: ``angle_deg`` [0] (direction, 0 = horizontal; null = random per frame),
  ``fraction`` [1.0] (share of frames blurred, chosen at random). Depth is not blurred.
- ``fast_motion``: keeps every (level + 1)-th frame (level an integer): frames 0, k, 2k, ...
  with k = level + 1. Timestamps and ground truth follow the kept frames.
- ``dropped_frames``: drops a fraction ``level`` in [0, 1) of the frames in bursts of ``burst``
  [5] consecutive frames at random places (frame 0 always stays). Timestamps and ground truth
  follow, so the stream has gaps.
- ``noise``: additive Gaussian noise of sigma ``level / 255`` (level = sigma in 8-bit grey
  levels) on every colour image, clipped to [0, 1]. Depth is untouched.
- ``depth_holes`` (RGB-D only): random discs (radius ``radius`` [0.08] x min(H, W), times
  0.5-1.5) are zeroed in the depth map until they cover at least a fraction ``level`` in [0, 1]
  of it (0 = invalid depth, as the readers deliver it).
- ``low_texture``: contrast reduction of the image towards its per-channel mean:
  ``rgb' = mean + (1 - level) * (rgb - mean)`` with level in [0, 1] (1 = a flat image). It works
  on every sequence, real or synthetic; for a scene that is itself poor in texture use the
  synthetic generator's ``data.texture=poor`` (or ``mixed``) knob instead.

Frames keep their ground-truth pose and timestamp; frame indices are renumbered 0..len-1 when
frames are skipped or dropped (``base_indices`` maps them back). Other attributes of the wrapped
sequence (e.g. ``dropped``, ``blank``) are forwarded unchanged.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Callable

import cv2
import numpy as np

from segs.data.base import normalize_index
from segs.data.frame import SENSORS, Frame, Sequence
from segs.errors import ConfigError

KEY = "data.stress"


# -- per-frame transforms (level > 0) -------------------------------------------------------------
def _colour(frame: Frame, fn: Callable[[np.ndarray], np.ndarray]) -> Frame:
    """Apply fn to the colour images (left and, for stereo, right)."""
    right = None if frame.right is None else fn(frame.right)
    return replace(frame, rgb=fn(frame.rgb), right=right)


def _exposure(frame: Frame, level: float, rng, pos: int, n: int, at: float = 0.5,
              direction: str = "down", wb: float = 0.25) -> Frame:  # fmt: skip
    """Gain / white-balance step of `level` stops from frame round(at * n) on."""
    if pos < round(at * n):
        return frame
    sign = 1.0 if direction == "up" else -1.0
    gain = (2.0 ** (sign * level + wb * level * np.array([1.0, 0.0, -1.0]))).astype(np.float32)
    return _colour(frame, lambda im: np.clip(im * gain, 0.0, 1.0).astype(np.float32))


def line_kernel(length: float, angle_deg: float) -> np.ndarray:
    """Normalised [K,K] float32 kernel of a line `length` pixels long at `angle_deg` (anti-aliased)."""
    size = 2 * int(math.ceil(length / 2)) + 1
    kernel = np.zeros((size, size), np.float64)
    c = (size - 1) / 2
    t = np.linspace(-(length - 1) / 2, (length - 1) / 2, max(int(length * 8), 2))
    x = c + t * math.cos(math.radians(angle_deg))
    y = c + t * math.sin(math.radians(angle_deg))
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    for dx, dy, w in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        np.add.at(kernel, (np.clip(y0 + dy, 0, size - 1), np.clip(x0 + dx, 0, size - 1)), w)
    return (kernel / kernel.sum()).astype(np.float32)


def _motion_blur(frame: Frame, level: float, rng, pos: int, n: int, angle_deg: float | None = 0.0,
                 fraction: float = 1.0) -> Frame:  # fmt: skip
    """Linear blur of level % of the image width; a random `fraction` of the frames."""
    blurred, random_angle = rng.random() < fraction, rng.uniform(0.0, 180.0)
    if not blurred:
        return frame
    length = max(level / 100.0 * frame.rgb.shape[1], 1.0)
    kernel = line_kernel(length, random_angle if angle_deg is None else float(angle_deg))
    return _colour(frame, lambda im: cv2.filter2D(im, -1, kernel, borderType=cv2.BORDER_REFLECT))


def _noise(frame: Frame, level: float, rng, pos: int, n: int) -> Frame:
    """Additive Gaussian noise, sigma = level / 255, clipped."""
    sigma = level / 255.0
    return _colour(frame, lambda im: np.clip(im + rng.normal(0.0, sigma, im.shape), 0.0, 1.0).astype(np.float32))


def hole_mask(shape: tuple[int, int], fraction: float, radius: float, rng) -> np.ndarray:
    """bool [H,W] mask of random discs covering at least `fraction` of the image."""
    h, w = shape
    mask = np.zeros(shape, np.uint8)
    target = math.ceil(fraction * h * w)
    r0 = max(radius * min(h, w), 1.0)
    while int(mask.sum()) < target:
        for _ in range(8):
            centre = (int(rng.integers(0, w)), int(rng.integers(0, h)))
            cv2.circle(mask, centre, max(int(round(r0 * rng.uniform(0.5, 1.5))), 1), 1, thickness=-1)
    return mask.astype(bool)


def _depth_holes(frame: Frame, level: float, rng, pos: int, n: int, radius: float = 0.08) -> Frame:
    """Zero random discs of the depth map covering a fraction `level` of it."""
    depth = frame.depth.copy()
    depth[hole_mask(depth.shape, level, radius, rng)] = 0.0
    return replace(frame, depth=depth)


def _low_texture(frame: Frame, level: float, rng, pos: int, n: int) -> Frame:
    """Contrast reduced by `level` towards the left image's per-channel mean."""
    mean = frame.rgb.reshape(-1, 3).mean(0).astype(np.float32)
    keep = np.float32(1.0 - level)
    return _colour(frame, lambda im: np.clip(mean + keep * (im - mean), 0.0, 1.0).astype(np.float32))


# -- frame selection (level > 0) -----------------------------------------------------------------
def _every_kth(n: int, level: float, rng) -> np.ndarray:
    return np.arange(0, n, int(level) + 1)


def _drop_bursts(n: int, level: float, rng, burst: int = 5) -> np.ndarray:
    """Indices kept after dropping bursts covering round(level * n) frames (frame 0 kept)."""
    target = min(int(round(level * n)), n - 1)
    dropped = np.zeros(n, bool)
    while (left := target - int(dropped.sum())) > 0:
        start = int(rng.integers(1, n))
        burst_frames = start + np.nonzero(~dropped[start:])[0][: min(int(burst), left)]
        dropped[burst_frames] = True
    return np.nonzero(~dropped)[0]


# -- the registry --------------------------------------------------------------------------------
def _number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


@dataclass(frozen=True)
class StressKind:
    """One generator: level check, per-frame transform or frame selection, accepted options."""

    levels_ok: Callable[[float], bool]
    levels: str
    transform: Callable | None = None
    select: Callable | None = None
    options: dict = field(default_factory=dict)
    sensors: tuple = SENSORS


KINDS: dict[str, StressKind] = {
    "exposure": StressKind(lambda v: v >= 0, "a number of stops >= 0", _exposure,
                           options={"at": 0.5, "direction": "down", "wb": 0.25}),  # fmt: skip
    "motion_blur": StressKind(lambda v: v >= 0, "a blur length in % of the image width >= 0", _motion_blur,
                              options={"angle_deg": 0.0, "fraction": 1.0}),  # fmt: skip
    "fast_motion": StressKind(lambda v: v >= 0 and float(v).is_integer(), "an integer >= 0 (frames skipped)",
                              select=_every_kth),  # fmt: skip
    "dropped_frames": StressKind(lambda v: 0 <= v < 1, "a fraction in [0, 1)", select=_drop_bursts,
                                 options={"burst": 5}),  # fmt: skip
    "noise": StressKind(lambda v: v >= 0, "a sigma in 8-bit grey levels >= 0", _noise),
    "depth_holes": StressKind(lambda v: 0 <= v <= 1, "a fraction in [0, 1]", _depth_holes,
                              options={"radius": 0.08}, sensors=("rgbd",)),  # fmt: skip
    "low_texture": StressKind(lambda v: 0 <= v <= 1, "a fraction in [0, 1]", _low_texture),
}


def _check_options(kind: str, spec: StressKind, options: dict) -> dict:
    unknown = sorted(set(options) - set(spec.options))
    if unknown:
        accepted = ", ".join(sorted(spec.options)) or "none"
        raise ConfigError(f"{KEY}: unknown option {unknown[0]!r} for kind {kind!r} (accepted: {accepted})")
    merged = {**spec.options, **options}
    checks = {
        "at": lambda v: _number(v) and 0 <= v <= 1,
        "direction": lambda v: v in ("up", "down"),
        "wb": _number,
        "angle_deg": lambda v: v is None or _number(v),
        "fraction": lambda v: _number(v) and 0 <= v <= 1,
        "burst": lambda v: _number(v) and v >= 1 and float(v).is_integer(),
        "radius": lambda v: _number(v) and 0 < v <= 1,
    }
    for name, value in merged.items():
        if not checks[name](value):
            raise ConfigError(f"{KEY}.{name}={value!r} is out of range for kind {kind!r}")
    return merged


def check(kind, level, sensor: str | None = None, options: dict | None = None) -> dict:
    """Validate a stress spec; returns its options with defaults. ConfigError naming data.stress."""
    if kind not in KINDS:
        raise ConfigError(f"{KEY}.kind={kind!r} is unknown: expected one of {', '.join(KINDS)}")
    spec = KINDS[kind]
    if not _number(level) or not spec.levels_ok(level):
        raise ConfigError(f"{KEY}.level={level!r} is out of range for kind {kind!r}: expected {spec.levels}")
    if sensor is not None and sensor not in spec.sensors:
        raise ConfigError(f"{KEY}.kind={kind!r} needs a {' or '.join(spec.sensors)} sequence, got sensor {sensor!r}")
    return _check_options(kind, spec, dict(options or {}))


class StressedSequence(Sequence):
    """A sequence whose frames are degraded by one stress generator (see the module doc).

    Attributes: name, sensor, camera as the wrapped one; timestamps / gt_poses of the kept frames;
    base (the wrapped sequence), base_indices [N] (wrapped index of each frame), stress (the spec).
    """

    def __init__(self, base: Sequence, kind: str, level: float, seed: int = 0, **options):
        self.options = check(kind, level, base.sensor, options)
        self.base, self.kind, self.level, self.seed = base, kind, float(level), int(seed)
        self.stress = {"kind": kind, "level": self.level, "seed": self.seed, **self.options}
        self.name, self.sensor, self.camera = base.name, base.sensor, base.camera
        spec = KINDS[kind]
        self._transform = spec.transform if self.level > 0 else None
        n = len(base)
        if spec.select is not None and self.level > 0 and n > 0:
            rng = np.random.default_rng([self.seed, list(KINDS).index(kind)])
            self.base_indices = spec.select(n, self.level, rng, **self.options)
        else:
            self.base_indices = np.arange(n)
        self.timestamps = np.asarray(base.timestamps)[self.base_indices]
        self.gt_poses = None if base.gt_poses is None else np.asarray(base.gt_poses)[self.base_indices]

    def __getattr__(self, name: str):
        if name == "base":
            raise AttributeError(name)
        return getattr(self.base, name)

    def __len__(self) -> int:
        return len(self.base_indices)

    def __getitem__(self, index: int) -> Frame:
        i = normalize_index(index, len(self))
        b = int(self.base_indices[i])
        frame = self.base[b]
        if self._transform is not None:
            rng = np.random.default_rng([self.seed, list(KINDS).index(self.kind), b])
            frame = self._transform(frame, self.level, rng, b, len(self.base), **self.options)
        return frame if frame.index == i else replace(frame, index=i)

    def __repr__(self) -> str:
        return f"StressedSequence({self.base!r}, {self.kind}={self.level:g}, {len(self)} frames)"


def apply_stress(sequence: Sequence, kind: str, level: float, seed: int = 0, **options) -> Sequence:
    """`sequence` degraded by the stress generator `kind` at `level` (0 = identity); see module doc.

    Raises ConfigError naming data.stress for an unknown kind, an out-of-range level or option,
    or a kind the sensor cannot take (depth_holes without depth).
    """
    if not isinstance(seed, int) or isinstance(seed, bool) or seed < 0:
        raise ConfigError(f"{KEY}.seed={seed!r} is out of range: expected an integer >= 0")
    return StressedSequence(sequence, kind, level, seed, **options)
