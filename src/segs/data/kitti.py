"""KITTI odometry reader (one sequence folder of the odometry benchmark's layout).

Layout (Geiger, Lenz, Urtasun, CVPR 2012; the devkit's readme):
- ``image_0/NNNNNN.png`` left and ``image_1/`` right greyscale, ``image_2/`` left and ``image_3/``
  right colour images; rectified, undistorted; frame i is ``{i:06d}.png``;
- ``calib.txt``: lines ``P0: ...`` to ``P3: ...`` (and ``Tr: ...``), each a row-major 3x4
  projection matrix of a rectified camera, ``P_i = K [I | t_i]`` in the frame of camera 0; the
  stereo baseline of a pair is the distance between the two camera centres ``-K^-1 P_i[:, 3]``;
- ``times.txt``: one timestamp (seconds) per frame;
- ground truth: ``poses.txt`` in the folder, or the benchmark's ``poses/NN.txt`` beside
  ``sequences/NN``: one row-major 3x4 camera-to-world matrix of camera 0 per frame, in the frame
  of the first one (metres; x right, y down, z forward, as OpenCV).
The colour cameras sit a few centimetres from camera 0: their ground truth is camera 0's moved by
their centre offset (``c2w_0 @ [I | c_i]``). Grey images are replicated to 3 channels.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from segs.data.base import ReaderSequence, check_sensor, frame_range, gt_pose
from segs.data.files import check_increasing, image_shape, read_numeric, read_rgb, read_rows, require_dir, to_float
from segs.data.frame import Camera, Frame
from segs.data.poses import check_rigid
from segs.errors import DataError

FOLDERS = {False: ("image_0", "image_1"), True: ("image_2", "image_3")}  # colour -> (left, right)
SKEW_TOLERANCE = 1e-9  # |K[0,1]|, |K[1,0]|, |K[2,:2]| and |K[2,2] - 1| accepted as rounding


def read_calib(path: Path) -> dict[str, np.ndarray]:
    """calib.txt ``NAME: 12 numbers`` lines -> name -> [3,4] float64 (names as written, e.g. "P0")."""
    out = {}
    for lineno, fields in read_rows(path, (2, 64)):
        name = fields[0]
        if not name.endswith(":"):
            raise DataError(f"{path}:{lineno}: expected 'NAME: 12 numbers', got {name[:20]!r} first")
        values = [to_float(tok, path, lineno) for tok in fields[1:]]
        if len(values) != 12:
            raise DataError(f"{path}:{lineno}: {name[:-1]} has {len(values)} numbers, expected 12 (a 3x4 matrix)")
        out[name[:-1]] = np.array(values).reshape(3, 4)
    return out


def projection(calib: dict[str, np.ndarray], name: str, path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(K [3,3], centre [3] in camera 0's frame) of the rectified camera of matrix `name`."""
    if name not in calib:
        raise DataError(f"{path}: no '{name}:' line (needed for this sensor)")
    P = calib[name]
    K = P[:, :3]
    off = [abs(K[0, 1]), abs(K[1, 0]), abs(K[2, 0]), abs(K[2, 1]), abs(K[2, 2] - 1.0)]
    if max(off) > SKEW_TOLERANCE or not (K[0, 0] > 0 and K[1, 1] > 0):
        raise DataError(f"{path}: {name} is not a rectified pinhole projection K [I | t] "
                        "(positive focal lengths, no skew, last row 0 0 1 t)")
    return K, -np.linalg.solve(K, P[:, 3])


def read_times(path: Path) -> np.ndarray:
    """times.txt -> [N] float64 seconds, finite and strictly increasing."""
    data, linenos = read_numeric(path, (1, 1))
    times = data[:, 0]
    check_increasing(times, path, linenos)
    if not len(times):
        raise DataError(f"{path}: no timestamps listed")
    return times


def read_poses(path: Path, n: int) -> np.ndarray:
    """poses.txt (one row-major 3x4 camera-to-world matrix per line) -> [n,4,4] float64."""
    data, linenos = read_numeric(path, (12, 12))
    if len(data) != n:
        raise DataError(f"{path}: {len(data)} poses for {n} frames in times.txt, expected one per frame")
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :] = data.reshape(n, 3, 4)
    check_rigid(poses, path, linenos)
    return poses


class KittiSequence(ReaderSequence):
    """A KITTI odometry sequence folder in sensor mode "mono" (left camera) or "stereo" (the pair).

    Args:
        root: the sequence folder (image_0/, calib.txt, times.txt, optional poses.txt).
        sensor: "mono" or "stereo" (needs image_1/, or image_3/ with color).
        color: the colour cameras (image_2 / image_3, P2 / P3) instead of the greyscale ones.
        frames: [start, stop) frame numbers to read (None: all).
        downscale: image/intrinsics reduction factor >= 1.
        poses: ground-truth file; None: root/poses.txt, else the benchmark's
            root/../../poses/<root name>.txt, else no ground truth.
    Attributes: baseline (stereo, metres, from calib.txt), frame_numbers [N] int64.
    """

    def __init__(self, root: str | Path, sensor: str = "mono", color: bool = False, frames=None,
                 downscale: float = 1, poses: str | Path | None = None, name: str | None = None):
        self.root = require_dir(root, "KITTI sequence folder")
        left, right = FOLDERS[bool(color)]
        require_dir(self.root / left, f"KITTI {left} folder")
        check_sensor(sensor, {"mono": None, "stereo": None if (self.root / right).is_dir() else f"no {right} folder",
                              "rgbd": "KITTI has no depth camera"}, self.root)
        self.sensor, self.color, self.dropped = sensor, bool(color), 0
        self.name = name or self.root.resolve().name
        times = read_times(self.root / "times.txt")
        numbers_ = np.arange(len(times), dtype=np.int64)
        keep = frame_range(frames, numbers_)
        if not keep.any():
            raise DataError(f"{self.root / 'times.txt'}: no frame in data.frames={list(frames)} of {len(times)}")
        self.frame_numbers, self.timestamps = numbers_[keep], times[keep]
        self.left_paths = self._images(left)
        self.right_paths = self._images(right) if sensor == "stereo" else None
        centre = self._calibrate(left, right, downscale)
        self.gt_poses = self._ground_truth(poses, len(times), keep, centre)

    def _images(self, folder: str) -> list[Path]:
        """The images of the selected frames in `folder`; DataError naming the first missing one."""
        paths = [self.root / folder / f"{i:06d}.png" for i in self.frame_numbers.tolist()]
        for p in paths:
            if not p.is_file():
                raise DataError(f"{p}: image not found (times.txt lists {len(self.frame_numbers)} frames)")
        return paths

    def _calibrate(self, left: str, right: str, downscale: float) -> np.ndarray:
        """Sets the camera (and baseline); returns the left camera's centre in camera 0's frame [3]."""
        path = self.root / "calib.txt"
        calib = read_calib(path)
        names = {"image_0": "P0", "image_1": "P1", "image_2": "P2", "image_3": "P3"}
        K, centre = projection(calib, names[left], path)
        baseline = None
        if self.sensor == "stereo":
            K_r, centre_r = projection(calib, names[right], path)
            baseline = float(centre_r[0] - centre[0])
            if not np.allclose(K_r, K, rtol=0, atol=1e-6) or not baseline > 0:
                raise DataError(f"{path}: {names[right]} is not the right camera of a rectified pair with "
                                f"{names[left]} (same K, centre to the right); baseline {baseline:.4f} m")
        self.shape = image_shape(self.left_paths[0])
        h, w = self.shape
        self.set_camera(Camera(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), w, h, baseline),
                        downscale)
        return centre

    def _ground_truth(self, poses, n: int, keep: np.ndarray, centre: np.ndarray) -> np.ndarray | None:
        if poses is not None:
            path = Path(poses)
        else:
            path = self.root / "poses.txt"
            if not path.is_file():
                path = self.root.parent.parent / "poses" / f"{self.root.name}.txt"
            if not path.is_file():
                return None
        offset = np.eye(4)
        offset[:3, 3] = centre  # camera 0 -> this camera (rectified: same rotation)
        return read_poses(path, n)[keep] @ offset

    def __len__(self) -> int:
        return len(self.timestamps)

    def load(self, index: int) -> Frame:
        rgb = read_rgb(self.left_paths[index], self.shape)
        right = None if self.right_paths is None else read_rgb(self.right_paths[index], self.shape)
        return Frame(index, float(self.timestamps[index]), rgb, self.native_camera, None, right,
                     gt_pose(self.gt_poses, index), self.left_paths[index].name)
