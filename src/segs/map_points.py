"""The SLAM map points of a run: gathered from the frontend's MapUpdates, written as a PLY.

`MapPointLog` keeps every point the frontend handed over (positions at creation, moved with
their keyframe by loop corrections exactly as the mapper moves what they created);
`write_map_points` / `read_map_points` store them as `map_points.ply` (x y z, red green blue
uchar, kf_id int: the keyframe that created each point), which segs.track and segs.train write
and segs.view shows. Imports nothing of segs but the errors.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyElement, PlyParseError

from segs.errors import DataError

FILE_NAME = "map_points.ply"


class MapPointLog:
    """Map points [M,3] float64, colours [M,3] float32 in [0,1], creating kf ids [M] int64."""

    def __init__(self) -> None:
        self.points = np.zeros((0, 3), np.float64)
        self.colors = np.zeros((0, 3), np.float32)
        self.kf_ids = np.zeros(0, np.int64)

    def __len__(self) -> int:
        return len(self.points)

    def add(self, update) -> None:
        """Apply a MapUpdate (segs.slam.base): its loop corrections move the points of each
        corrected keyframe (world-to-world similarity [4,4]), then its new points are appended
        (as the bridge hands them to the mapper: corrections first)."""
        for kf_id, T in update.corrections.items():
            mask = self.kf_ids == int(kf_id)
            if mask.any():
                T = np.asarray(T, np.float64)
                self.points[mask] = self.points[mask] @ T[:3, :3].T + T[:3, 3]
        if len(update.points):
            self.points = np.concatenate([self.points, np.asarray(update.points, np.float64)])
            self.colors = np.concatenate([self.colors, np.asarray(update.colors, np.float32)])
            self.kf_ids = np.concatenate([self.kf_ids, np.asarray(update.point_kf, np.int64)])

    def write(self, path: str | Path) -> int:
        return write_map_points(path, self.points, self.colors, self.kf_ids)

    def state_dict(self) -> dict:
        return {"points": self.points, "colors": self.colors, "kf_ids": self.kf_ids}

    def load_state_dict(self, state: dict) -> None:
        self.points = np.asarray(state["points"], np.float64).reshape(-1, 3)
        self.colors = np.asarray(state["colors"], np.float32).reshape(-1, 3)
        self.kf_ids = np.asarray(state["kf_ids"], np.int64).reshape(-1)


def write_map_points(path: str | Path, points: np.ndarray, colors: np.ndarray, kf_ids: np.ndarray) -> int:
    """points [M,3], colors [M,3] in [0,1], kf_ids [M] -> binary PLY, written to a temporary name
    and renamed (a partial file never looks finished); returns M."""
    arr = np.empty(len(points), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1"),
                                       ("kf_id", "i4")])  # fmt: skip
    for i, a in enumerate("xyz"):
        arr[a] = points[:, i]
    rgb = (np.clip(colors, 0, 1) * 255 + 0.5).astype(np.uint8)
    for i, a in enumerate(("red", "green", "blue")):
        arr[a] = rgb[:, i]
    arr["kf_id"] = kf_ids
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    PlyData([PlyElement.describe(arr, "vertex")]).write(str(tmp))
    tmp.replace(path)
    return len(arr)


def read_map_points(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(points [M,3] float64, colors [M,3] float32 in [0,1], kf_ids [M] int64) of a map_points.ply;
    DataError naming the file when it is not one."""
    try:
        v = PlyData.read(str(path))["vertex"]
        points = np.stack([v[a] for a in "xyz"], 1).astype(np.float64)
        colors = np.stack([v[a] for a in ("red", "green", "blue")], 1).astype(np.float32) / 255.0
        kf_ids = np.asarray(v["kf_id"], np.int64)
    except (OSError, KeyError, ValueError, PlyParseError) as err:
        raise DataError(f"{path}: not a map points PLY ({' '.join(str(err).split())[:120]})") from None
    return points, colors, kf_ids
