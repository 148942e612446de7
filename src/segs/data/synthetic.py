"""Synthetic sequences rendered by ray casting a procedural textured room (numpy, vectorised).

A test fixture and stress generator with exact poses and depth, never a stand-in for the real
readers. Conventions: OpenCV camera (x right, y down, z forward), camera-to-world ground truth,
world z up (see :mod:`segs.data.synthetic_scene` for the room and the corridor), timestamps
``index / 30`` s.

Knobs:

- ``trajectory``: ``"loop"`` (an ellipse of radii 1.5 x 1.1 m around the room centre at about
  1.4 m height, height/yaw/pitch/roll varying periodically, looking 25-45 degrees outward from
  the direction of travel), ``"line"`` (a sideways translation along x looking at the +y wall,
  drifting 0.3 m forward, small rotations; ping-pong over a 3 m segment) or ``"orbit"``
  (a circle of radius 1.3 m looking at the room centre) or ``"pan"`` (rotation in place: the
  camera stays at the room centre, 1.4 m high, and turns its yaw once around per lap with a
  small pitch nod; every surface point is seen along one viewing ray whatever the frame), or
  ``"forward"`` (driving / walking: down a 5 m wide, 80 m long corridor with pillars and low
  blocks along its walls, looking ahead, weaving +-0.6 m sideways with +-6 degrees of yaw; depths
  from about 1 m to 70 m; the only trajectory in the corridor, the others are in the room).
- ``speed``: for ``loop``, ``orbit`` and ``pan`` the number of laps over the whole sequence; for ``line``
  the number of times the 3 m segment is travelled (back and forth); for ``forward`` the number
  of 24 m stretches travelled (at most 2.9: the corridor ends). The frame angle is
  ``2 pi speed i / (n_frames - 1)``: speed 2 = twice the motion between consecutive frames for a
  fixed ``n_frames``. The last frame is back at the first pose whenever ``speed`` is an integer
  (loop, orbit) or an even integer (line) -- with the default ``speed=1`` a loop closes exactly.
- ``exposure_change``: amplitude A in stops (log2): ``rgb = clip(gain(i) * wb(i) * texture)``
  with ``gain(i) = 2 ** (A sin(2 pi i / 24 + 0.7))`` and per-channel white balance
  ``wb_c(i) = 2 ** (0.25 A sin(2 pi i / 37 + 2.1 c))``. Smooth in the frame index (no step),
  and not periodic with the trajectory, so revisits see another exposure. 0 = none.
- ``texture``: ``"rich"`` (high-contrast shapes, many ORB corners), ``"poor"`` (every surface
  smooth and low contrast) or ``"mixed"`` (the +-x walls and the ceiling poor, the rest rich).
- ``blank_frames``: frame indices rendered as a uniform grey (0.5) image (left and right);
  their depth and pose stay exact. Items are ints or ``(start, stop)`` half-open ranges, e.g.
  ``[3, (10, 15)]`` or ``range(10, 15)``.
- ``sensor``: ``"mono"``, ``"stereo"`` (right image from the camera shifted by +baseline along
  its x axis, ``Camera.baseline`` set) or ``"rgbd"`` (exact z-depth in metres, not ray length).
"""
from __future__ import annotations

from collections import OrderedDict
from typing import Iterable

import numpy as np

from segs.data.frame import SENSORS, Camera, Frame, Sequence
from segs.data.synthetic_scene import CORRIDOR, TEXTURES, get_scene
from segs.errors import ConfigError

TRAJECTORIES = ("loop", "line", "orbit", "pan", "forward")
#: metres of corridor per unit of `speed` on the forward trajectory, and its start (y)
FORWARD_STRETCH = 24.0
FORWARD_START = -1.0
FPS = 30.0
_CACHE_FRAMES = 32


def look_pose(position: np.ndarray, forward: np.ndarray, roll: float = 0.0) -> np.ndarray:
    """c2w [4,4] of an OpenCV camera at position [3] looking along forward [3], world z up."""
    f = forward / np.linalg.norm(forward)
    r = np.cross(f, [0.0, 0.0, 1.0])
    r /= np.linalg.norm(r)
    down = np.cross(f, r)
    c, s = np.cos(roll), np.sin(roll)
    r, down = c * r + s * down, -s * r + c * down
    pose = np.eye(4)
    pose[:3, :3] = np.stack([r, down, f], axis=1)
    pose[:3, 3] = position
    return pose


def _direction(yaw: float, pitch: float) -> np.ndarray:
    return np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)])


def _loop_pose(theta: float) -> np.ndarray:
    pos = np.array([1.5 * np.cos(theta), 1.1 * np.sin(theta), 1.4 + 0.15 * np.sin(2 * theta)])
    tangent_yaw = np.arctan2(1.1 * np.cos(theta), -1.5 * np.sin(theta))
    yaw = tangent_yaw - np.radians(35.0 + 10.0 * np.sin(3 * theta))  # outward = to the right
    pitch = np.radians(-5.0 + 5.0 * np.sin(theta))
    return look_pose(pos, _direction(yaw, pitch), np.radians(3.0 * np.sin(2 * theta)))


def _line_pose(theta: float) -> np.ndarray:
    u = np.arccos(np.cos(theta)) / np.pi  # triangle wave: 0 -> 1 over [0, pi], back by 2 pi
    pos = np.array([-1.5 + 3.0 * u, -1.0 + 0.3 * u, 1.3 + 0.1 * np.sin(2 * np.pi * u)])
    yaw = np.radians(90.0 + 8.0 * np.sin(2 * np.pi * u))
    pitch = np.radians(-8.0 + 3.0 * np.cos(2 * np.pi * u))
    return look_pose(pos, _direction(yaw, pitch), np.radians(2.0 * np.sin(np.pi * u)))


def _orbit_pose(theta: float) -> np.ndarray:
    pos = np.array([1.3 * np.cos(theta), 1.3 * np.sin(theta), 1.5])
    return look_pose(pos, np.array([0.0, 0.0, 0.8]) - pos)


def _pan_pose(theta: float) -> np.ndarray:
    pitch = np.radians(-5.0 + 4.0 * np.sin(2 * theta))
    return look_pose(np.array([0.0, 0.0, 1.4]), _direction(theta, pitch))


def _forward_pose(s: float) -> np.ndarray:
    """Pose after s metres along the corridor (+y): weaving sideways, looking ahead."""
    w = 2 * np.pi * s
    pos = np.array([0.6 * np.sin(w / 23.0), FORWARD_START + s, 1.5 + 0.1 * np.sin(w / 7.0)])
    yaw = np.radians(90.0 + 6.0 * np.sin(w / 17.0 + 0.5))
    pitch = np.radians(-2.0 + 2.0 * np.sin(w / 11.0))
    return look_pose(pos, _direction(yaw, pitch), np.radians(1.5 * np.sin(w / 13.0)))


def trajectory_poses(kind: str, n_frames: int, speed: float = 1.0) -> np.ndarray:
    """Camera-to-world poses [n_frames,4,4] float64 of a named trajectory (see module doc)."""
    make = {"loop": _loop_pose, "line": _line_pose, "orbit": _orbit_pose, "pan": _pan_pose,
            "forward": _forward_pose}[kind]
    thetas = 2 * np.pi * speed * np.arange(n_frames) / max(n_frames - 1, 1)
    if kind == "line":
        thetas = thetas / 2  # one segment traversal per unit of speed
    elif kind == "forward":  # metres along the corridor
        thetas = thetas * FORWARD_STRETCH / (2 * np.pi)
    return np.stack([make(t) for t in thetas]) if n_frames else np.zeros((0, 4, 4))


def exposure(index: int, amplitude: float) -> np.ndarray:
    """Per-channel multiplicative exposure [3] float32 of frame `index` (gain times white balance)."""
    gain = 2.0 ** (amplitude * np.sin(2 * np.pi * index / 24 + 0.7))
    wb = 2.0 ** (0.25 * amplitude * np.sin(2 * np.pi * index / 37 + 2.1 * np.arange(3)))
    return (gain * wb).astype(np.float32)


def _blank_set(blank_frames: Iterable) -> frozenset[int]:
    """Frame indices from ints and (start, stop) half-open ranges."""
    out: set[int] = set()
    try:
        for item in blank_frames:
            if isinstance(item, (int, np.integer)):
                out.add(int(item))
            else:
                start, stop = item
                out.update(range(int(start), int(stop)))
    except (TypeError, ValueError):
        raise ConfigError(f"blank_frames must hold ints and (start, stop) pairs, "
                          f"got {blank_frames!r}") from None
    return frozenset(out)


def _check(sensor, n_frames, width, height, trajectory, texture, fov_deg, baseline, speed) -> None:
    max_speed = (CORRIDOR[1][1] - 6.0 - FORWARD_START) / FORWARD_STRETCH
    checks = [
        (sensor in SENSORS, f"sensor must be one of {SENSORS}, got {sensor!r}"),
        (trajectory in TRAJECTORIES, f"trajectory must be one of {TRAJECTORIES}, got {trajectory!r}"),
        (texture in TEXTURES, f"texture must be one of {TEXTURES}, got {texture!r}"),
        (n_frames >= 1 and width >= 2 and height >= 2, "n_frames >= 1, width, height >= 2 needed"),
        (0.0 < fov_deg < 170.0, f"fov_deg must be in (0, 170), got {fov_deg}"),
        (sensor != "stereo" or baseline > 0, f"stereo baseline must be > 0, got {baseline}"),
        (trajectory != "forward" or 0 <= speed <= max_speed,
         f"forward speed must be in [0, {max_speed:.2f}] (the corridor ends), got {speed}"),
    ]
    for ok, message in checks:
        if not ok:
            raise ConfigError(f"SyntheticSequence: {message}")


class SyntheticSequence(Sequence):
    """Procedural room (or corridor, for "forward") rendered by ray casting, with exact c2w poses and depth.

    Frames are rendered on demand and kept in a small LRU cache (32 frames). Rendering a
    320x240 frame takes a few milliseconds (twice that in stereo).
    Attributes: name, sensor, camera, timestamps [N] (index / 30 s), gt_poses [N,4,4] c2w,
    blank (frozenset of blank frame indices), dropped = 0.
    """

    def __init__(
        self,
        sensor: str = "rgbd",
        n_frames: int = 60,
        width: int = 320,
        height: int = 240,
        trajectory: str = "loop",
        speed: float = 1.0,
        exposure_change: float = 0.0,
        texture: str = "rich",
        blank_frames: Iterable = (),
        baseline: float = 0.1,
        seed: int = 0,
        fov_deg: float = 70.0,
    ):
        n_frames, width, height = int(n_frames), int(width), int(height)
        _check(sensor, n_frames, width, height, trajectory, texture, fov_deg, baseline, float(speed))
        self.sensor, self.exposure_change, self.dropped = sensor, float(exposure_change), 0
        self.name = f"synthetic_{trajectory}_{texture}"
        fx = float((width / 2.0) / np.tan(np.radians(fov_deg) / 2.0))
        self.camera = Camera(fx, fx, (width - 1) / 2.0, (height - 1) / 2.0, width, height,
                             float(baseline) if sensor == "stereo" else None)
        self.timestamps = np.arange(n_frames, dtype=np.float64) / FPS
        self.gt_poses = trajectory_poses(trajectory, n_frames, speed)
        self.blank = _blank_set(blank_frames)
        self._texture_seed = (texture, seed, "corridor" if trajectory == "forward" else "room")
        self._scene = get_scene(*self._texture_seed)
        u, v = np.meshgrid(np.arange(width), np.arange(height))
        self._rays = (((u - self.camera.cx) / fx).ravel().astype(np.float32),
                      ((v - self.camera.cy) / fx).ravel().astype(np.float32))
        self._cache: OrderedDict[int, Frame] = OrderedDict()

    def __len__(self) -> int:
        return len(self.timestamps)

    def __getstate__(self) -> dict:
        """Pickle without the shared scene and the frame cache (e.g. to DataLoader workers)."""
        state = dict(self.__dict__, _scene=None)
        state["_cache"] = OrderedDict()
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._scene = get_scene(*self._texture_seed)

    def render(self, c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Unexposed view from pose c2w [4,4]: rgb [H,W,3] float32 in [0,1], z-depth [H,W] float32."""
        shape = (self.camera.height, self.camera.width)
        rot = c2w[:3, :3].astype(np.float32)
        rx, ry = self._rays
        dirs = [rot[a, 0] * rx + rot[a, 1] * ry + rot[a, 2] for a in range(3)]
        origin = c2w[:3, 3].astype(np.float32)
        t, sid = self._scene.cast(origin, dirs)
        points = [origin[a] + t * dirs[a] for a in range(3)]
        footprint = self._scene.footprint(dirs, t, sid, self.camera.fx) if self._scene.mip_levels > 1 else None
        return self._scene.shade(points, sid, shape, footprint), t.reshape(shape)

    def _image(self, index: int, c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        rgb, depth = self.render(c2w)
        if index in self.blank:
            rgb = np.full_like(rgb, 0.5)
        elif self.exposure_change:
            rgb = np.clip(rgb * exposure(index, self.exposure_change), 0.0, 1.0)
        return rgb, depth

    def _make(self, index: int) -> Frame:
        pose = self.gt_poses[index]
        rgb, depth = self._image(index, pose)
        right = None
        if self.sensor == "stereo":
            shift = np.eye(4)
            shift[0, 3] = self.camera.baseline
            right = self._image(index, pose @ shift)[0]
        return Frame(index, float(self.timestamps[index]), rgb, self.camera,
                     depth if self.sensor == "rgbd" else None, right, pose.copy(),
                     f"{index:06d}")

    def __getitem__(self, index: int) -> Frame:
        n = len(self)
        if not -n <= index < n:
            raise IndexError(f"frame {index} out of range for {n} frames")
        index = int(index) % n
        frame = self._cache.get(index)
        if frame is None:
            frame = self._cache[index] = self._make(index)
            while len(self._cache) > _CACHE_FRAMES:
                self._cache.popitem(last=False)
        self._cache.move_to_end(index)
        return _copy(frame)


def _copy(frame: Frame) -> Frame:
    """A frame whose arrays the caller may modify without touching the cache."""
    def cp(a):
        return None if a is None else a.copy()
    return Frame(frame.index, frame.timestamp, frame.rgb.copy(), frame.camera, cp(frame.depth),
                 cp(frame.right), cp(frame.pose_c2w), frame.name)
