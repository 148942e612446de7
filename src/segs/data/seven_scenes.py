"""Microsoft 7-Scenes reader, in the dataset's native layout.

Dataset facts (Shotton et al., CVPR 2013): Kinect v1, 640x480 at 30 Hz; per frame
``frame-XXXXXX.color.png`` (or ``.color.jpg`` in some redistributions), ``frame-XXXXXX.depth.png``
(uint16 millimetres, 0 and 65535 invalid) and ``frame-XXXXXX.pose.txt`` (4x4 camera-to-world,
metres, from KinectFusion). The frames of a scene are grouped in ``seq-XX`` folders. There are no
timestamps: frame i is at i / fps seconds (fps = 30), the same convention as TUM-style index files
derived from the frames (``rgb.txt`` at i / 30), so both readers give the same frames and times.
The published intrinsics, 585, 585, 320, 240 (``camera-intrinsics.txt``, a 3x3 matrix), are the
DEPTH camera's, and the ground-truth poses are the depth camera's (KinectFusion on depth). The
colour camera is a different camera: its intrinsics and its pose relative to the depth camera are
not published. Measured here (docs/data.md "7-Scenes calibration", bench/calibrate_7scenes.py) from
the frames and the ground truth: COLOR_INTRINSICS and DEPTH_TO_COLOR below. The reader registers
the depth into the colour camera (cv2.registerDepth) and gives colour-camera ground truth, so that
`camera`, `depth` and `gt_poses` describe one camera, as in TUM RGB-D. Both lenses are undistorted
on load to the pinholes of their intrinsics (COLOR_DISTORTION, DEPTH_DISTORTION: measured, docs/data.md;
docs/decisions/034-seven-scenes-lens-distortion.md).

Lossless reference colour: a folder ``lossless_color*`` beside the sequence holding
``frame-XXXXXX.color.png`` copies of some frames (used to measure PSNR without JPEG artefacts)
is found automatically; :meth:`SevenScenesSequence.lossless_rgb` reads them.
"""
from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np

from segs.data.base import (DepthRegistration, ReaderSequence, check_sensor, frame_range, gt_pose, lens_maps, numbers,
                             pinhole, undistort)
from segs.data.files import image_shape, read_depth, read_numeric, read_rgb, require_dir
from segs.data.frame import Camera, Frame
from segs.data.poses import check_rigid
from segs.errors import ConfigError, DataError

DEPTH_INTRINSICS = (585.0, 585.0, 320.0, 240.0)  # published (camera-intrinsics.txt)
#: colour camera [fx, fy, cx, cy] and depth->colour transform [rx, ry, rz (rad), tx, ty, tz (m)],
#: measured by bench/calibrate_7scenes.py on redkitchen frames 0-599 (docs/data.md)
COLOR_INTRINSICS = (525.0, 525.0, 323.0, 240.0)
DEPTH_TO_COLOR = (0.0, 0.0, 0.0, -0.035, -0.005, 0.0)
#: colour and depth lens [k1, k2, p1, p2] (OpenCV), measured by bench/calibrate_7scenes.py --lens: the
#: same radial distortion for both lenses (docs/decisions/034-seven-scenes-lens-distortion.md)
COLOR_DISTORTION = (-0.1, 0.0, 0.0, 0.0)
DEPTH_DISTORTION = (-0.1, 0.0, 0.0, 0.0)
DEPTH_SCALE = 1000.0  # millimetres
DEPTH_INVALID = 65535
_COLOR = re.compile(r"^frame-(\d+)\.color\.(png|jpg)$")


def list_color(folder: Path) -> dict[int, Path]:
    """frame number -> colour image of a sequence folder (PNG preferred over JPEG)."""
    found: dict[int, Path] = {}
    for p in folder.iterdir():
        m = _COLOR.match(p.name)
        if m and (int(m.group(1)) not in found or m.group(2) == "png"):
            found[int(m.group(1))] = p
    return found


def find_sequence(root: Path, sequence: str | int | None) -> Path:
    """The folder holding frame-*.color.* files: root itself, root/<sequence> or its only seq-* folder."""
    if sequence is not None:
        name = f"seq-{int(sequence):02d}" if isinstance(sequence, int) or str(sequence).isdigit() else str(sequence)
        return require_dir(root / name, "7-Scenes sequence folder")
    if list_color(root):
        return root
    subs = sorted(p for p in root.iterdir() if p.is_dir() and p.name.startswith("seq") and list_color(p))
    if not subs:
        raise DataError(f"{root}: no frame-XXXXXX.color.png / .jpg images in it or in a seq-XX folder")
    if len(subs) > 1:
        names = ", ".join(p.name for p in subs)
        raise ConfigError(f"data.sequence: {root} holds several sequences ({names}); choose one")
    return subs[0]


def read_pose(path: Path) -> np.ndarray:
    """frame-XXXXXX.pose.txt -> [4,4] camera-to-world (finite, rigid)."""
    data, _ = read_numeric(path, (4, 4))
    if data.shape != (4, 4):
        raise DataError(f"{path}: expected a 4x4 matrix (4 lines of 4 numbers), got {len(data)} lines")
    check_rigid(data[None], path, what="pose")
    return data


def read_intrinsics(path: Path) -> tuple[float, float, float, float]:
    """camera-intrinsics.txt (3x3 matrix) -> (fx, fy, cx, cy)."""
    data, _ = read_numeric(path, (3, 3))
    if data.shape != (3, 3) or data[0, 1] != 0 or data[1, 0] != 0 or np.any(data[2] != [0, 0, 1]):
        raise DataError(f"{path}: expected a 3x3 pinhole matrix [[fx 0 cx] [0 fy cy] [0 0 1]]")
    return pinhole([data[0, 0], data[1, 1], data[0, 2], data[1, 2]], str(path))


class SevenScenesSequence(ReaderSequence):
    """A 7-Scenes sequence in sensor mode "rgbd" or "mono" (no stereo).

    Args:
        root: the sequence folder (frame-XXXXXX.* files) or a scene folder with seq-XX folders.
        sensor: "rgbd" or "mono".
        sequence: "seq-01" / 1 when root holds several sequences.
        frames: [start, stop) range of frame numbers to read (null = all), e.g. a short slice.
        downscale: image/intrinsics reduction factor >= 1.
        intrinsics: colour camera [fx, fy, cx, cy] (default: COLOR_INTRINSICS, measured).
        depth_intrinsics: depth camera [fx, fy, cx, cy] (default: root/camera-intrinsics.txt,
            else the published 585 585 320 240).
        depth_to_color: [rx, ry, rz, tx, ty, tz] depth->colour camera transform (default:
            DEPTH_TO_COLOR, measured). With the depth intrinsics as colour intrinsics and zeros
            here, the depth is used unregistered (the published convention).
        distortion: colour lens [k1, k2, p1, p2(, k3)] (OpenCV); the colour images are undistorted
            to the pinhole of `intrinsics` on load (default: COLOR_DISTORTION, measured; zeros: none).
        depth_distortion: depth lens, the same model; the depth is undistorted to the pinhole of
            `depth_intrinsics` before its registration (default: DEPTH_DISTORTION; zeros: none).
        depth_scale: depth PNG units per metre (1000: millimetres).
        fps: frame rate of the timestamps (frame number / fps).
    """

    def __init__(self, root: str | Path, sensor: str = "rgbd", sequence: str | int | None = None,
                 frames=None, downscale: float = 1, intrinsics=None, depth_intrinsics=None,
                 depth_to_color=None, depth_scale: float = DEPTH_SCALE, fps: float = 30.0,
                 name: str | None = None, distortion=None, depth_distortion=None):
        self.root = require_dir(root, "7-Scenes folder")
        check_sensor(sensor, {"mono": None, "rgbd": None, "stereo": "7-Scenes has no stereo camera"}, self.root)
        if not float(fps) > 0:
            raise ConfigError(f"data.fps must be positive, got {fps!r}")
        self.sensor, self.dropped, self.depth_scale = sensor, 0, float(depth_scale)
        self.folder = find_sequence(self.root, sequence)
        self.name = name or (self.root.resolve().name if self.folder == self.root else
                             f"{self.root.resolve().name}/{self.folder.name}")
        color = list_color(self.folder)
        numbers_ = np.array(sorted(color), np.int64)
        numbers_ = numbers_[frame_range(frames, numbers_)]
        if len(numbers_) == 0:
            raise DataError(f"{self.folder}: no frame in data.frames={list(frames)}")
        self.frame_numbers = numbers_
        self.rgb_paths = [color[int(i)] for i in numbers_]
        stem = [self.folder / f"frame-{int(i):06d}" for i in numbers_]
        self.depth_paths = [Path(f"{s}.depth.png") for s in stem] if sensor == "rgbd" else None
        for p in self.depth_paths or []:
            if not p.is_file():
                raise DataError(f"{p}: depth image not found")
        self.timestamps = numbers_.astype(np.float64) / float(fps)
        pose_paths = [Path(f"{s}.pose.txt") for s in stem]
        self._calibrate(intrinsics, depth_intrinsics, depth_to_color, depth_distortion, downscale)
        self._undistort_maps(distortion)
        self.gt_poses = None
        if any(p.is_file() for p in pose_paths):
            depth_c2w = np.stack([read_pose(p) if p.is_file() else np.full((4, 4), np.nan) for p in pose_paths])
            self.gt_poses = self.registration.color_poses(depth_c2w)
        self.lossless = self._find_lossless()

    def _find_lossless(self) -> dict[int, Path]:
        """Position in this sequence -> lossless colour PNG, from root/lossless_color* folders."""
        out: dict[int, Path] = {}
        pos = {int(n): i for i, n in enumerate(self.frame_numbers)}
        for d in sorted(self.root.glob("lossless_color*")):
            if d.is_dir():
                for n, p in list_color(d).items():
                    if n in pos and p.suffix == ".png":
                        out[pos[n]] = p
        return out

    def _calibrate(self, intrinsics, depth_intrinsics, depth_to_color, depth_distortion, downscale) -> None:
        self.shape = image_shape(self.rgb_paths[0])
        k = numbers(intrinsics, (4,), "data.intrinsics")
        fx, fy, cx, cy = pinhole(k, "data.intrinsics") if k is not None else COLOR_INTRINSICS
        self.set_camera(Camera(fx, fy, cx, cy, self.shape[1], self.shape[0]), downscale)
        file = self.root / "camera-intrinsics.txt"
        if depth_intrinsics is None:
            depth_intrinsics = read_intrinsics(file) if file.is_file() else DEPTH_INTRINSICS
        self.registration = DepthRegistration(
            depth_intrinsics, DEPTH_TO_COLOR if depth_to_color is None else depth_to_color, "data",
            DEPTH_DISTORTION if depth_distortion is None else depth_distortion)

    def _undistort_maps(self, distortion) -> None:
        """Remap tables from the colour lens [k1, k2, p1, p2(, k3)] (OpenCV's model; null: COLOR_DISTORTION)
        to the pinhole of the same intrinsics; none for zeros. The registered depth is already that
        pinhole's (cv2.registerDepth projects without a lens), so only colour is remapped."""
        self.distortion = numbers(COLOR_DISTORTION if distortion is None else distortion, (4, 5), "data.distortion")
        self._maps = lens_maps(self.native_camera.K, self.distortion, self.shape[::-1])

    def __len__(self) -> int:
        return len(self.rgb_paths)

    def load(self, index: int) -> Frame:
        rgb = undistort(read_rgb(self.rgb_paths[index], self.shape), self._maps, cv2.INTER_LINEAR)
        depth = None
        if self.depth_paths is not None:
            depth = read_depth(self.depth_paths[index], self.depth_scale, self.shape)
            depth[depth >= DEPTH_INVALID / self.depth_scale] = 0.0
            depth = self.registration.register(depth, self.native_camera)
        return Frame(index, float(self.timestamps[index]), rgb, self.native_camera, depth, None,
                     gt_pose(self.gt_poses, index), self.rgb_paths[index].name)

    def lossless_rgb(self, index: int) -> np.ndarray | None:
        """[H,W,3] float32 lossless colour of frame `index` at the delivered size, or None."""
        path = self.lossless.get(int(index))
        if path is None:
            return None
        rgb = undistort(read_rgb(path, self.shape), self._maps, cv2.INTER_LINEAR)
        if self.camera != self.native_camera:
            rgb = cv2.resize(rgb, (self.camera.width, self.camera.height), interpolation=cv2.INTER_AREA)
        return rgb

