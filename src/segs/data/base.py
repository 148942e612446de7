"""Shared machinery of the readers: sensor checks, downscaling, argument validation."""
from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np

from segs.data.frame import SENSORS, Camera, Frame, Sequence
from segs.errors import ConfigError, DataError


def check_sensor(sensor: str, supported: dict[str, str | None], where: object) -> None:
    """ConfigError for an unknown sensor name; DataError naming `where` when the dataset lacks it.

    supported: sensor -> None if available, else the reason it is not (one short phrase).
    """
    if sensor not in SENSORS:
        raise ConfigError(f"sensor must be one of {', '.join(SENSORS)}, got {sensor!r}")
    reason = supported.get(sensor, "not supported by this dataset")
    if reason is not None:
        usable = [s for s, r in supported.items() if r is None]
        available = ", ".join(usable) or "none"
        raise DataError(f"{where}: cannot provide sensor {sensor!r}: {reason} (available: {available})")


def check_factor(factor: float) -> float:
    """A downscale factor >= 1 as float, else ConfigError."""
    try:
        factor = float(factor)
    except (TypeError, ValueError):
        factor = float("nan")
    if not factor >= 1.0 or not np.isfinite(factor):
        raise ConfigError(f"downscale must be a number >= 1, got {factor!r}")
    return factor


def numbers(value, sizes: tuple[int, ...], key: str) -> np.ndarray | None:
    """A config list of finite numbers with an accepted length -> float64 array (None passes)."""
    if value is None:
        return None
    try:
        arr = np.asarray(list(value), dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError(f"{key} must be a list of numbers, got {value!r}") from None
    if arr.ndim != 1 or len(arr) not in sizes or not np.all(np.isfinite(arr)):
        raise ConfigError(f"{key} must be {' or '.join(map(str, sizes))} finite numbers, got {value!r}")
    return arr


def pinhole(intrinsics: np.ndarray, key: str = "intrinsics") -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) from [4] numbers, focal lengths positive."""
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    if fx <= 0 or fy <= 0:
        raise ConfigError(f"{key}: focal lengths must be positive, got fx={fx}, fy={fy}")
    return fx, fy, cx, cy


def lens_maps(K: np.ndarray, distortion: np.ndarray | None, size: tuple[int, int]):
    """Remap tables ([H,W] float32 x, y) from a lens [k1, k2, p1, p2(, k3)] (OpenCV's model) to the
    pinhole of the same K [3,3] at size (W, H); None for a pinhole lens (None or zeros)."""
    if distortion is None or not np.any(distortion != 0):
        return None
    return cv2.initUndistortRectifyMap(K, distortion, None, K, size, cv2.CV_32FC1)


def undistort(image: np.ndarray, maps, interpolation: int) -> np.ndarray:
    """An image [H,W(,C)] through the lens of `maps` (lens_maps) -> the pinhole's; itself for None; 0 outside."""
    if maps is None:
        return image
    return cv2.remap(image, *maps, interpolation, borderMode=cv2.BORDER_CONSTANT)


def resize_frame(frame: Frame, camera: Camera) -> Frame:
    """The frame resized to camera's size: area for images, nearest for depth; camera replaced."""
    size = (camera.width, camera.height)
    if frame.rgb.shape[1::-1] == size:
        return replace(frame, camera=camera)

    def image(a):
        return None if a is None else cv2.resize(a, size, interpolation=cv2.INTER_AREA)

    depth = None
    if frame.depth is not None:
        depth = cv2.resize(frame.depth, size, interpolation=cv2.INTER_NEAREST_EXACT)
    return replace(frame, rgb=image(frame.rgb), right=image(frame.right), depth=depth, camera=camera)


class DepthRegistration:
    """Depth of a separate depth camera mapped into the colour camera (unregistered RGB-D sensors).

    depth_intrinsics: [fx, fy, cx, cy] of the native depth image; depth_to_color: the rigid
    transform taking depth-camera coordinates to colour-camera coordinates, as 6 numbers
    [rx, ry, rz, tx, ty, tz] (rotation vector in radians, translation in metres; null: identity);
    depth_distortion: the depth lens [k1, k2, p1, p2(, k3)] (OpenCV's model; null or zeros: a
    pinhole), undistorted (nearest pixel) before the registration.
    Registration (cv2.registerDepth) back-projects every depth pixel, moves it into the colour
    camera and keeps the nearest depth per colour pixel (0 where none lands). The result is in the
    colour camera's pinhole: a colour lens is the reader's to undistort, not this depth's.
    """

    def __init__(self, depth_intrinsics, depth_to_color=None, key: str = "data", depth_distortion=None):
        fx, fy, cx, cy = pinhole(numbers(depth_intrinsics, (4,), f"{key}.depth_intrinsics"), f"{key}.depth_intrinsics")
        self.K_depth = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        self.T = np.eye(4)
        v = numbers(depth_to_color, (6,), f"{key}.depth_to_color")
        if v is not None:
            self.T[:3, :3] = cv2.Rodrigues(v[:3].reshape(3, 1))[0]
            self.T[:3, 3] = v[3:]
        self.depth_distortion = numbers(depth_distortion, (4, 5), f"{key}.depth_distortion")
        self._maps: dict[tuple[int, int], tuple[np.ndarray, np.ndarray] | None] = {}  # per depth (H, W)

    def register(self, depth: np.ndarray, color: Camera) -> np.ndarray:
        """depth [H,W] float32 metres (depth camera) -> [color.height, color.width] float32 (colour camera)."""
        if depth.shape not in self._maps:
            self._maps[depth.shape] = lens_maps(self.K_depth, self.depth_distortion, depth.shape[::-1])
        depth = undistort(depth, self._maps[depth.shape], cv2.INTER_NEAREST)
        if np.array_equal(self.T, np.eye(4)) and np.array_equal(self.K_depth, color.K) \
                and depth.shape == (color.height, color.width):
            return depth  # already registered (same camera)
        out = cv2.registerDepth(self.K_depth, color.K, None, self.T, np.ascontiguousarray(depth, np.float32),
                                (color.width, color.height))
        cv2.patchNaNs(out, 0.0)  # float images mark "no depth" with NaN (in place: 0.06 ms, nan_to_num 0.7)
        return out

    def color_poses(self, depth_c2w: np.ndarray) -> np.ndarray:
        """Camera-to-world poses of the depth camera [N,4,4] -> those of the colour camera [N,4,4]."""
        return depth_c2w @ np.linalg.inv(self.T)


def gt_pose(gt_poses: np.ndarray | None, index: int) -> np.ndarray | None:
    """Copy of the [4,4] ground-truth pose of a frame, None when absent or NaN."""
    if gt_poses is None or np.isnan(gt_poses[index]).any():
        return None
    return gt_poses[index].copy()


def normalize_index(index: int, n: int) -> int:
    """Python-style index into n frames, IndexError outside."""
    if not -n <= index < n:
        raise IndexError(f"frame {index} out of range for {n} frames")
    return int(index) % n


def frame_range(frames, numbers_: np.ndarray) -> np.ndarray:
    """Mask of frame numbers inside data.frames = [start, stop) (None: all)."""
    if frames is None:
        return np.ones(len(numbers_), bool)
    rng = numbers(frames, (2,), "data.frames")
    if rng[0] < 0 or rng[1] <= rng[0]:
        raise ConfigError(f"data.frames must be [start, stop) with 0 <= start < stop, got {list(frames)}")
    return (numbers_ >= rng[0]) & (numbers_ < rng[1])


class Downscaled(Sequence):
    """Any sequence with images, depth and intrinsics reduced by `factor` (>= 1; 1 = identity).

    Images use area interpolation, depth nearest (no mixing of foreground and background),
    intrinsics Camera.scaled(factor). Other attributes (dropped, ...) come from the wrapped one.
    """

    def __init__(self, sequence: Sequence, factor: float = 1.0):
        self.base, self.factor = sequence, check_factor(factor)
        self.name, self.sensor = sequence.name, sequence.sensor
        self.timestamps, self.gt_poses = sequence.timestamps, sequence.gt_poses
        self.camera = sequence.camera if self.factor == 1 else sequence.camera.scaled(self.factor)

    def __getattr__(self, name: str):
        if name == "base":
            raise AttributeError(name)
        return getattr(self.base, name)

    def __len__(self) -> int:
        return len(self.base)

    def __getitem__(self, index: int) -> Frame:
        return resize_frame(self.base[index], self.camera)


class ReaderSequence(Sequence):
    """Base of the file readers: lazy loading by :meth:`load`, downscaling by `downscale`.

    Subclasses set name, sensor, timestamps, gt_poses, dropped and call :meth:`set_camera` with
    the native (undistorted / rectified) camera; they implement len and load(index).
    """

    native_camera: Camera
    downscale: float = 1.0
    dropped: int = 0

    def set_camera(self, native: Camera, downscale: float) -> None:
        self.native_camera, self.downscale = native, check_factor(downscale)
        self.camera = native if self.downscale == 1 else native.scaled(self.downscale)

    def load(self, index: int) -> Frame:
        """The frame at full resolution (index already normalised)."""
        raise NotImplementedError

    def __getitem__(self, index: int) -> Frame:
        return resize_frame(self.load(normalize_index(index, len(self))), self.camera)

    def __repr__(self) -> str:
        cam = self.camera
        return (f"{type(self).__name__}({self.name!r}, sensor={self.sensor!r}, {len(self)} frames, "
                f"{cam.width}x{cam.height})")
