"""TUM RGB-D benchmark reader (rgb.txt, depth.txt, groundtruth.txt).

Dataset facts used here: depth PNG scale 5000 (1 m = 5000), the freiburg1/2/3 Kinect
calibrations below, and TUM's association rule (greedy pairing of the closest timestamps, at
most 0.02 s apart). The Camera always describes undistorted images: freiburg1/2 frames (colour
and depth alike) are undistorted with OpenCV on load, keeping the same intrinsic matrix.
"""
from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np

from segs.data.base import DepthRegistration, ReaderSequence, check_sensor, gt_pose, lens_maps, numbers, pinhole, undistort
from segs.data.files import (check_files_exist, check_increasing, image_shape, read_depth,
                             read_numeric, read_rgb, read_timestamped_paths, require_dir)
from segs.data.frame import Camera, Frame
from segs.data.poses import check_quaternions, interpolate_poses, poses_from_tq
from segs.errors import ConfigError, DataError

DEPTH_SCALE = 5000.0
#: freiburg camera -> (fx, fy, cx, cy), distortion (k1, k2, p1, p2, k3), from the TUM website.
FREIBURG = {
    1: ((517.3, 516.5, 318.6, 255.3), (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)),
    2: ((520.9, 521.0, 325.1, 249.7), (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)),
    3: ((535.4, 539.2, 320.1, 247.6), (0.0, 0.0, 0.0, 0.0, 0.0)),
}
_FREIBURG_NAME = re.compile(r"(?:^|[^a-z0-9])(?:freiburg|fr)([123])(?![0-9])")


def freiburg_of(folder: Path) -> int | None:
    """1, 2 or 3 when the folder name contains freiburgN or frN, else None."""
    match = _FREIBURG_NAME.search(folder.resolve().name.lower())
    return int(match.group(1)) if match else None


def associate(first: np.ndarray, second: np.ndarray, max_difference: float) -> tuple[np.ndarray, np.ndarray]:
    """TUM's association: greedily pair the closest timestamps, each used once, |dt| < max.

    first [N], second [M] increasing seconds -> index arrays (i [K], j [K]) sorted by i.
    """
    lo = np.searchsorted(second, first - max_difference, side="left")
    hi = np.searchsorted(second, first + max_difference, side="right")
    cand_i = np.repeat(np.arange(len(first)), hi - lo)
    cand_j = np.concatenate([np.arange(a, b) for a, b in zip(lo, hi)] or [np.zeros(0, int)]).astype(int)
    diff = np.abs(first[cand_i] - second[cand_j])
    keep = diff < max_difference
    cand_i, cand_j, diff = cand_i[keep], cand_j[keep], diff[keep]
    used_i, used_j, pairs = set(), set(), []
    for k in np.lexsort((cand_j, cand_i, diff)):
        i, j = int(cand_i[k]), int(cand_j[k])
        if i not in used_i and j not in used_j:
            used_i.add(i), used_j.add(j), pairs.append((i, j))
    pairs.sort()
    arr = np.array(pairs, dtype=int).reshape(-1, 2)
    return arr[:, 0], arr[:, 1]


def read_tum_trajectory(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """TUM trajectory 'timestamp tx ty tz qx qy qz qw' -> (times [M], c2w poses [M,4,4]).

    Checks: 8 finite numbers per line, strictly increasing timestamps, unit quaternions.
    """
    data, linenos = read_numeric(path, (8, 8))
    check_increasing(data[:, 0], path, linenos)
    check_quaternions(data[:, 4:8], path, linenos)
    return data[:, 0], poses_from_tq(data[:, 1:4], data[:, 4:8])


class TumSequence(ReaderSequence):
    """A TUM RGB-D sequence folder in sensor mode "mono" or "rgbd" (TUM has no stereo).

    Args:
        root: folder with rgb.txt (+ depth.txt for rgbd, optional groundtruth.txt).
        sensor: "rgbd" (needs depth.txt) or "mono".
        downscale: image/intrinsics reduction factor >= 1.
        intrinsics: [fx, fy, cx, cy] overriding the freiburg preset.
        distortion: [k1, k2, p1, p2(, k3)] overriding the preset (zeros when neither is known).
        freiburg: 1, 2 or 3 to pick the preset; default: from the folder name (freiburgN / frN).
        max_difference: rgb-depth association tolerance in seconds (TUM: 0.02).
        gt_max_difference: ground-truth interpolation / nearest tolerance in seconds.
        depth_scale: depth PNG units per metre (TUM: 5000).
        depth_intrinsics, depth_to_color: for depth NOT registered to the colour camera (TUM's is):
            the depth camera's [fx, fy, cx, cy] and the depth->colour transform
            [rx, ry, rz, tx, ty, tz]; the depth is then registered into the colour camera and the
            ground truth, taken as the depth camera's, is moved to the colour camera
            (segs.data.base.DepthRegistration). Both null: depth used as is.
        depth_distortion: the depth lens [k1, k2, p1, p2(, k3)] of unregistered depth (with
            depth_intrinsics), undistorted before the registration (null: a pinhole).
    Attributes: dropped = colour frames left out for lack of a depth partner; frame timestamps
    are the rgb.txt timestamps; gt_poses [N,4,4] c2w (NaN where no ground truth) or None.
    """

    def __init__(self, root: str | Path, sensor: str = "rgbd", downscale: float = 1,
                 intrinsics=None, distortion=None, freiburg: int | None = None,
                 max_difference: float = 0.02, gt_max_difference: float = 0.1,
                 depth_scale: float = DEPTH_SCALE, depth_intrinsics=None, depth_to_color=None,
                 name: str | None = None, depth_distortion=None):
        self.root = require_dir(root, "TUM sequence folder")
        has_depth = (self.root / "depth.txt").is_file()
        check_sensor(sensor, {"mono": None, "rgbd": None if has_depth else "no depth.txt",
                              "stereo": "TUM RGB-D has no stereo camera"}, self.root)
        self.sensor, self.name = sensor, name or self.root.resolve().name
        self.depth_scale = float(depth_scale)
        self._index(float(max_difference))
        self.registration = None
        if depth_intrinsics is not None or depth_to_color is not None or depth_distortion is not None:
            if depth_intrinsics is None:
                raise ConfigError("data.depth_to_color / data.depth_distortion need data.depth_intrinsics "
                                  "(the depth camera's [fx, fy, cx, cy])")
            self.registration = DepthRegistration(depth_intrinsics, depth_to_color, "data", depth_distortion)
        self._ground_truth(float(gt_max_difference))
        self._calibrate(intrinsics, distortion, freiburg, downscale)

    def _index(self, max_difference: float) -> None:
        rgb_txt = self.root / "rgb.txt"
        times, names, lines = read_timestamped_paths(rgb_txt)
        if not len(times):
            raise DataError(f"{rgb_txt}: no images listed")
        self.rgb_paths = check_files_exist(self.root, names, rgb_txt, lines)
        self.depth_paths = None
        if self.sensor == "rgbd":
            depth_txt = self.root / "depth.txt"
            dtimes, dnames, dlines = read_timestamped_paths(depth_txt)
            depth_paths = check_files_exist(self.root, dnames, depth_txt, dlines)
            i, j = associate(times, dtimes, max_difference)
            if not len(i):
                raise DataError(f"{depth_txt}: no depth image within {max_difference} s of any "
                                f"colour image of {rgb_txt}")
            self.rgb_paths = [self.rgb_paths[k] for k in i]
            self.depth_paths = [depth_paths[k] for k in j]
            times = times[i]
        self.dropped = len(names) - len(times)
        self.timestamps = times

    def _ground_truth(self, max_difference: float) -> None:
        path = self.root / "groundtruth.txt"
        self.gt_poses = None
        if path.is_file():
            gt_times, gt = read_tum_trajectory(path)
            self.gt_poses = interpolate_poses(gt_times, gt, self.timestamps, max_difference)
            if self.registration is not None:
                self.gt_poses = self.registration.color_poses(self.gt_poses)

    def _calibrate(self, intrinsics, distortion, freiburg, downscale) -> None:
        if freiburg is not None and freiburg not in FREIBURG:
            raise ConfigError(f"freiburg must be 1, 2 or 3, got {freiburg!r}")
        preset = FREIBURG.get(freiburg or freiburg_of(self.root))
        k = numbers(intrinsics, (4,), "intrinsics")
        if k is None and preset is None:
            raise DataError(f"{self.root}: cannot tell the freiburg camera from the folder name; "
                            "pass freiburg=1|2|3 or intrinsics=[fx, fy, cx, cy]")
        fx, fy, cx, cy = pinhole(k if k is not None else preset[0])
        d = numbers(distortion, (4, 5), "distortion")
        d = d if d is not None else np.array(preset[1] if preset else (0.0,) * 5)
        h, w = self.shape = image_shape(self.rgb_paths[0])
        self.distortion = d
        self.set_camera(Camera(fx, fy, cx, cy, w, h), downscale)
        self._maps = lens_maps(self.native_camera.K, d, (w, h))

    def __len__(self) -> int:
        return len(self.timestamps)

    def load(self, index: int) -> Frame:
        rgb = undistort(read_rgb(self.rgb_paths[index], self.shape), self._maps, cv2.INTER_LINEAR)
        depth = None
        if self.depth_paths is not None:
            depth = read_depth(self.depth_paths[index], self.depth_scale, self.shape)
            if self.registration is None:  # depth registered to the colour image, through its lens
                depth = undistort(depth, self._maps, cv2.INTER_NEAREST)
            else:  # registered here into the colour camera's pinhole: no colour lens to undo
                depth = self.registration.register(depth, self.native_camera)
        path = self.rgb_paths[index]
        name = str(path.relative_to(self.root) if path.is_relative_to(self.root) else path)
        return Frame(index, float(self.timestamps[index]), rgb, self.native_camera, depth, None,
                     gt_pose(self.gt_poses, index), name)
