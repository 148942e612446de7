"""Replica reader, in the layout packaged by NICE-SLAM (``results/``, ``traj.txt``).

Dataset facts: ``results/frameNNNNNN.jpg`` colour and ``results/depthNNNNNN.png`` 16-bit depth
with scale 6553.5 (1 m = 6553.5), ``traj.txt`` with one camera-to-world 4x4 matrix per frame
(16 numbers per line, row-major, OpenCV camera axes), images 1200x680, fx = fy = 600,
cx = 599.5, cy = 339.5, no distortion. The files carry no timestamps: frame i gets i / fps
seconds (fps = 30 by default).
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from segs.data.base import ReaderSequence, check_sensor, gt_pose, numbers, pinhole
from segs.data.files import image_shape, read_depth, read_numeric, read_rgb, require_dir
from segs.data.frame import Camera, Frame
from segs.data.poses import check_rigid
from segs.errors import ConfigError, DataError

DEPTH_SCALE = 6553.5
INTRINSICS = (600.0, 600.0, 599.5, 339.5)
IMAGE_SIZE = (1200, 680)  # width, height
_FRAME = re.compile(r"^frame(\d+)\.(jpg|png)$")


def list_frames(results: Path) -> list[Path]:
    """results/frame*.jpg (or .png) sorted by frame number; DataError when there are none."""
    found = [(int(m.group(1)), p) for p in results.iterdir() if (m := _FRAME.match(p.name))]
    if not found:
        raise DataError(f"{results}: no frame*.jpg images")
    return [p for _, p in sorted(found)]


def read_traj(path: Path) -> np.ndarray:
    """NICE-SLAM traj.txt -> c2w poses [N,4,4]; 16 finite numbers per line, rigid transforms."""
    data, linenos = read_numeric(path, (16, 16))
    poses = data.reshape(-1, 4, 4)
    check_rigid(poses, path, linenos)
    return poses


class ReplicaSequence(ReaderSequence):
    """A NICE-SLAM Replica scene folder in sensor mode "rgbd" or "mono" (no stereo).

    Args:
        root: scene folder with results/ and traj.txt (traj.txt optional: gt_poses None).
        sensor: "rgbd" or "mono".
        downscale: image/intrinsics reduction factor >= 1.
        intrinsics: [fx, fy, cx, cy] overriding 600 600 599.5 339.5 (needed for images of
            another size than 1200x680).
        depth_scale: depth PNG units per metre (6553.5).
        fps: frame rate used for timestamps = index / fps.
    """

    def __init__(self, root: str | Path, sensor: str = "rgbd", downscale: float = 1,
                 intrinsics=None, depth_scale: float = DEPTH_SCALE, fps: float = 30.0,
                 name: str | None = None):
        self.root = require_dir(root, "Replica scene folder")
        check_sensor(sensor, {"mono": None, "rgbd": None, "stereo": "Replica has no stereo pair"}, self.root)
        if not float(fps) > 0:
            raise ConfigError(f"fps must be positive, got {fps!r}")
        self.sensor, self.name, self.dropped = sensor, name or self.root.resolve().name, 0
        self.depth_scale = float(depth_scale)
        results = require_dir(self.root / "results", "Replica results folder")
        self.rgb_paths = list_frames(results)
        self.depth_paths = None
        if sensor == "rgbd":
            self.depth_paths = [results / _FRAME.sub(r"depth\1.png", p.name) for p in self.rgb_paths]
            missing = [p for p in self.depth_paths if not p.is_file()]
            if missing:
                raise DataError(f"{missing[0]}: depth image not found "
                                f"({len(missing)} missing for {len(self.rgb_paths)} frames)")
        self.timestamps = np.arange(len(self.rgb_paths), dtype=np.float64) / float(fps)
        self._ground_truth()
        self._calibrate(intrinsics, downscale)

    def _ground_truth(self) -> None:
        path = self.root / "traj.txt"
        self.gt_poses = None
        if path.is_file():
            poses = read_traj(path)
            if len(poses) != len(self.rgb_paths):
                raise DataError(f"{path}: {len(poses)} poses for {len(self.rgb_paths)} frames in "
                                "results/, expected one per frame")
            self.gt_poses = poses

    def _calibrate(self, intrinsics, downscale) -> None:
        h, w = self.shape = image_shape(self.rgb_paths[0])
        k = numbers(intrinsics, (4,), "intrinsics")
        if k is None and (w, h) != IMAGE_SIZE:
            raise DataError(f"{self.rgb_paths[0]}: image is {w}x{h}, expected 1200x680 "
                            "(NICE-SLAM Replica); pass intrinsics=[fx, fy, cx, cy] for other sizes")
        fx, fy, cx, cy = pinhole(k if k is not None else INTRINSICS)
        self.set_camera(Camera(fx, fy, cx, cy, w, h), downscale)

    def __len__(self) -> int:
        return len(self.rgb_paths)

    def load(self, index: int) -> Frame:
        rgb = read_rgb(self.rgb_paths[index], self.shape)
        depth = None
        if self.depth_paths is not None:
            depth = read_depth(self.depth_paths[index], self.depth_scale, self.shape)
        return Frame(index, float(self.timestamps[index]), rgb, self.native_camera, depth, None,
                     gt_pose(self.gt_poses, index), self.rgb_paths[index].name)
