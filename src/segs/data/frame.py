"""Frame and camera records shared by every reader, the SLAM frontend and the mapper.

Everything here is numpy; nothing knows about training.
"""
from __future__ import annotations

import abc
from dataclasses import dataclass, replace
from typing import Iterator

import numpy as np

SENSORS = ("mono", "stereo", "rgbd")


@dataclass(frozen=True)
class Camera:
    """Pinhole intrinsics of an undistorted (for stereo: rectified) image stream.

    baseline: stereo baseline in metres between the rectified left and right cameras, else None.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    baseline: float | None = None

    @property
    def K(self) -> np.ndarray:
        """[3,3] float64 intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def scaled(self, factor: float) -> "Camera":
        """Intrinsics of the image resized by 1/factor (pixel-centre convention)."""
        w, h = int(round(self.width / factor)), int(round(self.height / factor))
        sx, sy = w / self.width, h / self.height
        return replace(
            self,
            fx=self.fx * sx,
            fy=self.fy * sy,
            cx=(self.cx + 0.5) * sx - 0.5,
            cy=(self.cy + 0.5) * sy - 0.5,
            width=w,
            height=h,
        )


@dataclass
class Frame:
    """One time step of a sequence.

    rgb:      [H,W,3] float32 in [0,1] (grey sources are replicated to 3 channels)
    depth:    [H,W] float32 metres, 0 where invalid; None without a depth sensor
    right:    [H,W,3] float32 rectified right image (stereo), else None
    pose_c2w: [4,4] float64 ground-truth camera-to-world pose, None where unknown
    """

    index: int
    timestamp: float
    rgb: np.ndarray
    camera: Camera
    depth: np.ndarray | None = None
    right: np.ndarray | None = None
    pose_c2w: np.ndarray | None = None
    name: str = ""


class Sequence(abc.ABC):
    """An indexable image stream in one sensor mode ("mono", "stereo" or "rgbd").

    Frames are loaded lazily by __getitem__. timestamps: [N] float64 seconds, increasing.
    gt_poses: [N,4,4] float64 camera-to-world ground truth, NaN-filled where unknown, or None.
    """

    name: str
    sensor: str
    camera: Camera
    timestamps: np.ndarray
    gt_poses: np.ndarray | None

    @abc.abstractmethod
    def __len__(self) -> int: ...

    @abc.abstractmethod
    def __getitem__(self, index: int) -> Frame: ...

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self[i]
