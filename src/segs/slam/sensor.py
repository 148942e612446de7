"""SensorSetup: what tracking, local mapping and loop closing know of the camera and the features."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from segs.data.frame import Camera


@dataclass(frozen=True, eq=False)
class SensorSetup:
    """The sensor as the SLAM components see it (built once by the frontend, never changed).

    camera: image size and intrinsics; sensor: "mono" | "stereo" | "rgbd"; K [3,3]; bf: fx x
    baseline (stereo: the rig's; RGB-D: the virtual one of tracking.rgbd_baseline; ORB-SLAM's
    mbf); th_depth: "close" depth (ORB-SLAM's ThDepth, metres); ur_sigma: constant sigma (pixels)
    of the virtual right coordinate of RGB-D keypoints, None otherwise; scales [L] / sigma2 [L]:
    scale and squared scale of each pyramid level; scale_factor: between levels; n_features:
    keypoints per image.
    """

    camera: Camera
    sensor: str
    K: np.ndarray
    bf: float
    th_depth: float
    ur_sigma: float | None
    scales: np.ndarray
    sigma2: np.ndarray
    scale_factor: float
    n_features: int

    @property
    def mono(self) -> bool:
        return self.sensor == "mono"

    def backproject(self, uv: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Camera-frame points [N,3] of pixels uv [N,2] at depths [N]."""
        K = self.K
        return np.stack([(uv[:, 0] - K[0, 2]) / K[0, 0] * depth, (uv[:, 1] - K[1, 2]) / K[1, 1] * depth, depth], 1)
