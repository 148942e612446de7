"""A run folder read back for `python -m segs.view`: what kind of run it is, how far it got, and
the files the viewer shows (trajectory, keyframes, map points, Gaussians of point_cloud.ply,
metrics). Nothing here builds the mapper: segs.view does, from the checkpoint found here.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from omegaconf import DictConfig, OmegaConf
from plyfile import PlyData, PlyParseError

from segs.errors import DataError
from segs.map_points import FILE_NAME as MAP_POINTS
from segs.map_points import read_map_points
from segs.trajectory import read_tum
from segs.viewer.scene import Splats

SH_C0 = 0.28209479177387814  # the degree-0 SH constant of the 3D-GS PLY layout


@dataclass
class SavedRun:
    """kind: "train" or "track"; status: finished / not_evaluated / tracking_failed / interrupted.

    trajectory: (timestamps [M], c2w [M,4,4]) of trajectory.txt (trajectory_partial.txt when
    interrupted) or None; keyframes: (kf_id, frame_index) of keyframes.txt (track runs);
    points: (points [P,3], colors [P,3]) of map_points.ply or None; checkpoint: final.ckpt, else
    last.ckpt, or None; ply: point_cloud.ply or None; results: metrics.json / tracking.json.
    """

    path: Path
    kind: str
    status: str
    config: DictConfig
    results: dict = field(default_factory=dict)
    trajectory: tuple[np.ndarray, np.ndarray] | None = None
    keyframes: list[tuple[int, int]] = field(default_factory=list)
    points: tuple[np.ndarray, np.ndarray] | None = None
    checkpoint: Path | None = None
    ply: Path | None = None

    def w2c_at(self, timestamp: float) -> np.ndarray | None:
        """[4,4] world-to-camera pose of the trajectory at `timestamp` (within 0.1 ms), or None."""
        if self.trajectory is None:
            return None
        stamps, c2w = self.trajectory
        near = np.flatnonzero(np.abs(stamps - timestamp) < 1e-4)
        return np.linalg.inv(c2w[near[0]]) if len(near) else None


def read_run(path: str | Path) -> SavedRun:
    """The run in `path`; DataError (one line) when it is not a run folder or holds nothing to show."""
    path = Path(path)
    if not path.is_dir():
        raise DataError(f"{path}: no such folder (give the folder of a segs.train or segs.track run)")
    config_file = path / ".hydra" / "config.yaml"
    if not config_file.is_file():
        raise DataError(f"{path}: not a run folder (no .hydra/config.yaml; give the folder of a segs.train or segs.track run)")
    try:
        config = OmegaConf.load(config_file)
    except Exception as err:  # noqa: BLE001 - yaml / OmegaConf parse errors of a damaged file
        raise DataError(f"{config_file}: unreadable ({' '.join(str(err).split())[:120]})") from None
    kind = "track" if (path / "tracking.json").is_file() or (path / "keyframes.txt").is_file() else "train"
    results_file = path / ("tracking.json" if kind == "track" else "metrics.json")
    results = json.loads(results_file.read_text()) if results_file.is_file() else {}
    ckpts = [path / "checkpoints" / n for n in ("final.ckpt", "last.ckpt") if (path / "checkpoints" / n).is_file()]
    run = SavedRun(path, kind, results.get("status", "finished") if results else "interrupted", config, results,
                   checkpoint=ckpts[0] if ckpts else None,
                   ply=path / "point_cloud.ply" if (path / "point_cloud.ply").is_file() else None)  # fmt: skip
    for name in ("trajectory.txt", "trajectory_partial.txt"):
        if (path / name).is_file():
            run.trajectory = read_tum(path / name)
            break
    if (path / "keyframes.txt").is_file():
        rows = np.loadtxt(path / "keyframes.txt", comments="#", ndmin=2)
        run.keyframes = [(int(r[0]), int(r[1])) for r in rows]
    if (path / MAP_POINTS).is_file():
        run.points = read_map_points(path / MAP_POINTS)[:2]
    if run.trajectory is None and run.checkpoint is None and run.ply is None and not results:
        raise DataError(f"{path}: the run saved nothing to show yet (no trajectory, checkpoint, point_cloud.ply or results)")
    return run


def read_gaussian_ply(path: str | Path) -> Splats:
    """The Gaussians of a 3D-GS PLY (x y z f_dc_* opacity scale_* rot_*), coloured by their
    degree-0 SH (view-independent; f_rest_* are not evaluated)."""
    try:
        v = PlyData.read(str(path))["vertex"]
        col = lambda *names: np.stack([np.asarray(v[n], np.float32) for n in names], 1)  # noqa: E731
        means, dc = col("x", "y", "z"), col("f_dc_0", "f_dc_1", "f_dc_2")
        opacity = 1.0 / (1.0 + np.exp(-np.asarray(v["opacity"], np.float32)))
        scales, quats = np.exp(col("scale_0", "scale_1", "scale_2")), col("rot_0", "rot_1", "rot_2", "rot_3")
    except (OSError, KeyError, ValueError, PlyParseError) as err:
        raise DataError(f"{path}: not a 3D-GS PLY ({' '.join(str(err).split())[:120]})") from None
    quats /= np.linalg.norm(quats, axis=1, keepdims=True).clip(1e-12)
    return Splats(means, quats, scales, opacity, np.clip(dc * SH_C0 + 0.5, 0, 1))
