"""EuRoC MAV reader (ASL layout: mav0/cam0, mav0/cam1, mav0/state_groundtruth_estimate0).

- stereo: both cameras rectified with OpenCV (stereoRectify with alpha 0 and zero disparity at
  infinity, initUndistortRectifyMap, remap) from the two sensor.yaml calibrations; the Camera is
  that of the rectified left image, with the baseline in metres. The rectified left camera is
  rotated by R1 from cam0, so its ground truth is T_WB @ T_BS(cam0) @ R1^T.
- mono: the left camera undistorted (not rectified) with its own intrinsic matrix; ground truth
  T_WB @ T_BS(cam0).
Timestamps are nanoseconds in the files and seconds in the frames. Stereo pairs are formed by
equal timestamps (the cameras are triggered together); unpaired left frames are dropped and
counted. Grey images are replicated to 3 channels.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml

from segs.data.base import ReaderSequence, check_sensor, gt_pose
from segs.data.files import (check_files_exist, check_increasing, image_shape, read_numeric, read_rgb,
                             read_rows, require_dir, require_file, to_int)
from segs.data.frame import Camera, Frame
from segs.data.poses import check_quaternions, check_rigid, interpolate_poses, poses_from_tq
from segs.errors import DataError


@dataclass(frozen=True)
class EurocCamera:
    """One sensor.yaml: K [3,3], dist [4] radial-tangential, size (width, height), T_BS [4,4]."""

    K: np.ndarray
    dist: np.ndarray
    size: tuple[int, int]
    T_BS: np.ndarray


MIN_BASELINE_M = 1e-3  # cam0-cam1 distance below which a pair is not a stereo rig

def _field(data: dict, key: str, n: int, path: Path) -> np.ndarray:
    value = data.get(key)
    if isinstance(value, dict):
        value = value.get("data")
    try:
        arr = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError, OverflowError):
        raise DataError(f"{path}: '{key}' must be a list of {n} numbers") from None
    if len(arr) != n or not np.all(np.isfinite(arr)):
        raise DataError(f"{path}: '{key}' must be a list of {n} finite numbers")
    return arr


def read_calibration(path: str | Path) -> EurocCamera:
    """Parse an EuRoC camera sensor.yaml (its '%YAML:1.0' first line is dropped for PyYAML)."""
    path = require_file(path, "camera calibration")
    try:
        text = path.read_text(encoding="utf-8")
        lines = text.splitlines()
        if lines and lines[0].startswith("%YAML"):
            text = "\n".join(lines[1:])
        data = yaml.safe_load(text)
    except (OSError, UnicodeDecodeError, yaml.YAMLError, ValueError, TypeError, OverflowError,
            RecursionError) as exc:
        raise DataError(f"{path}: cannot parse YAML ({type(exc).__name__})") from None
    if not isinstance(data, dict):
        raise DataError(f"{path}: expected a YAML mapping with intrinsics, distortion_coefficients, "
                        "resolution, T_BS")
    for key, want in (("camera_model", "pinhole"), ("distortion_model", "radial-tangential")):
        if data.get(key, want) != want:
            raise DataError(f"{path}: {key} {data.get(key)!r} is not supported, expected {want!r}")
    fx, fy, cx, cy = _field(data, "intrinsics", 4, path)
    w, h = _field(data, "resolution", 2, path)
    if fx <= 0 or fy <= 0 or w < 1 or h < 1 or w != int(w) or h != int(h):
        raise DataError(f"{path}: expected positive focal lengths and an integer resolution")
    T = _field(data, "T_BS", 16, path).reshape(1, 4, 4)
    check_rigid(T, path, what="T_BS")
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    return EurocCamera(K, _field(data, "distortion_coefficients", 4, path), (int(w), int(h)), T[0])


def read_image_index(cam: Path) -> tuple[np.ndarray, list[Path]]:
    """camN/data.csv 'timestamp [ns],filename' -> (ns [N] int64 increasing, image paths)."""
    csv = cam / "data.csv"
    rows = read_rows(csv, (2, 2), sep=",")
    ns = np.array([to_int(f[0], csv, n, "timestamp in ns") for n, f in rows], dtype=np.int64)
    linenos = [n for n, _ in rows]
    check_increasing(ns, csv, linenos)
    if not len(ns):
        raise DataError(f"{csv}: no images listed")
    return ns, check_files_exist(cam / "data", [f[1] for _, f in rows], csv, linenos)


def read_groundtruth(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """state_groundtruth_estimate0/data.csv -> (ns [M] int64, T_WB [M,4,4])."""
    rows = read_rows(path, (8, 64), sep=",")
    linenos = [n for n, _ in rows]
    ns = np.array([to_int(f[0], path, n, "timestamp in ns") for n, f in rows], dtype=np.int64)
    data, _ = read_numeric(path, (8, 64), sep=",")
    check_increasing(ns, path, linenos)
    quat = data[:, [5, 6, 7, 4]]  # (w, x, y, z) -> (x, y, z, w)
    check_quaternions(quat, path, linenos)
    return ns, poses_from_tq(data[:, 1:4], quat)


def _homogeneous(rot: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = rot
    return out


class EurocSequence(ReaderSequence):
    """A EuRoC MAV sequence (folder containing mav0/, or mav0 itself), "stereo" or "mono".

    Args:
        root: sequence folder.
        sensor: "stereo" (rectified pair) or "mono" (undistorted left camera).
        downscale: image/intrinsics reduction factor >= 1.
        gt_max_difference: ground-truth interpolation / nearest tolerance in seconds.
    Attributes: dropped = left frames without a right frame of the same timestamp (stereo);
    rectify_rotation [3,3] = R1 (cam0 -> rectified left, identity in mono).
    """

    def __init__(self, root: str | Path, sensor: str = "stereo", downscale: float = 1,
                 gt_max_difference: float = 0.1, name: str | None = None):
        self.root = require_dir(root, "EuRoC sequence folder")
        mav = self.root / "mav0" if (self.root / "mav0").is_dir() else self.root
        require_dir(mav / "cam0", "EuRoC cam0 folder")
        check_sensor(sensor, {"mono": None, "stereo": None if (mav / "cam1").is_dir() else "no cam1 folder",
                              "rgbd": "EuRoC has no depth camera"}, self.root)
        self.sensor, self.mav = sensor, mav
        self.name = name or (self.root if mav != self.root else self.root.parent).resolve().name
        self._index()
        self._calibrate(downscale)
        self._ground_truth(float(gt_max_difference))

    def _index(self) -> None:
        ns, self.left_paths = read_image_index(self.mav / "cam0")
        self.right_paths, self.dropped = None, 0
        if self.sensor == "stereo":
            ns_right, right_paths = read_image_index(self.mav / "cam1")
            common, il, ir = np.intersect1d(ns, ns_right, assume_unique=True, return_indices=True)
            if not len(common):
                csv = self.mav / "cam1" / "data.csv"
                raise DataError(f"{csv}: no timestamp in common with cam0/data.csv")
            self.dropped = len(ns) - len(common)
            self.left_paths = [self.left_paths[i] for i in il]
            self.right_paths = [right_paths[i] for i in ir]
            ns = common
        self.timestamps_ns = ns
        self.timestamps = ns / 1e9

    def _calibrate(self, downscale: float) -> None:
        left = read_calibration(self.mav / "cam0" / "sensor.yaml")
        self.shape = left.size[::-1]
        if image_shape(self.left_paths[0]) != self.shape:
            w, h = left.size
            raise DataError(f"{self.left_paths[0]}: image is not {w}x{h} as in cam0/sensor.yaml")
        if self.sensor == "mono":
            self.rectify_rotation = np.eye(3)
            self._maps = [cv2.initUndistortRectifyMap(left.K, left.dist, None, left.K, left.size,
                                                      cv2.CV_32FC1)]
            fx, fy, cx, cy = (float(v) for v in (left.K[0, 0], left.K[1, 1], left.K[0, 2], left.K[1, 2]))
            self.set_camera(Camera(fx, fy, cx, cy, *left.size), downscale)
        else:
            right = read_calibration(self.mav / "cam1" / "sensor.yaml")
            if right.size != left.size:
                path = self.mav / "cam1" / "sensor.yaml"
                raise DataError(f"{path}: resolution {right.size} differs from cam0's {left.size}")
            self._rectify(left, right, downscale)
        self.T_BS = left.T_BS

    def _rectify(self, left: EurocCamera, right: EurocCamera, downscale: float) -> None:
        T_rl = np.linalg.inv(right.T_BS) @ left.T_BS  # cam0 coordinates -> cam1 coordinates
        if not np.linalg.norm(T_rl[:3, 3]) > MIN_BASELINE_M:
            raise DataError(f"{self.mav / 'cam1' / 'sensor.yaml'}: T_BS puts cam1 {np.linalg.norm(T_rl[:3, 3]):.4f} m from cam0; "
                            f"a stereo pair needs a baseline > {MIN_BASELINE_M} m")  # fmt: skip
        R1, R2, P1, P2, *_ = cv2.stereoRectify(left.K, left.dist, right.K, right.dist, left.size,
                                               T_rl[:3, :3].copy(), T_rl[:3, 3:4].copy(),
                                               flags=cv2.CALIB_ZERO_DISPARITY, alpha=0)
        self.rectify_rotation = R1
        self._maps = [cv2.initUndistortRectifyMap(c.K, c.dist, R, P, left.size, cv2.CV_32FC1)
                      for c, R, P in ((left, R1, P1), (right, R2, P2))]
        baseline = float(-P2[0, 3] / P2[0, 0])
        if not baseline > 0:  # cam1 must be the right camera after rectification
            raise DataError(f"{self.mav / 'cam1' / 'sensor.yaml'}: rectified baseline {baseline:.4f} m; expected cam1 "
                            "to the right of cam0 (> 0)")  # fmt: skip
        fx, fy, cx, cy = (float(v) for v in (P1[0, 0], P1[1, 1], P1[0, 2], P1[1, 2]))
        self.set_camera(Camera(fx, fy, cx, cy, *left.size, baseline), downscale)

    def _ground_truth(self, max_difference: float) -> None:
        path = self.mav / "state_groundtruth_estimate0" / "data.csv"
        self.gt_poses = None
        if path.is_file():
            ns, T_WB = read_groundtruth(path)
            T_WB = interpolate_poses(ns / 1e9, T_WB, self.timestamps, max_difference)
            self.gt_poses = T_WB @ self.T_BS @ _homogeneous(self.rectify_rotation.T)

    def __len__(self) -> int:
        return len(self.timestamps)

    def _image(self, path: Path, maps) -> np.ndarray:
        return cv2.remap(read_rgb(path, self.shape), *maps, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)

    def load(self, index: int) -> Frame:
        rgb = self._image(self.left_paths[index], self._maps[0])
        right = None if self.right_paths is None else self._image(self.right_paths[index], self._maps[1])
        return Frame(index, float(self.timestamps[index]), rgb, self.native_camera, None, right,
                     gt_pose(self.gt_poses, index), self.left_paths[index].name)
