"""RunState: what a run knows of its frames beside the Gaussian map.

It owns

- the frame source (segs.pipeline.sources): the trajectory, lost and dropped frames, the
  frontend's keyframes and the tracking speed are read from it, nowhere else;
- the split: a keyframe whose frame index is a multiple of `holdout_every` is held out (never a
  training view, its map points never reach the mapper); the test views are the tracked frames
  whose image no training view holds;
- the keyframe registry: kf_id -> frame index, latest pose and role (training view or held out)
  of every keyframe handed over. The mapper's training views (and through them its appearance
  embedding) are fed from it in one place, `route()`, by the bridge callback;
- the SLAM map points handed over (segs.map_points.MapPointLog: map_points.ply, the viewer).

`route()` turns one MapUpdate into what the mapper receives; `finish()` ends the sequence and
replaces every keyframe pose by the final trajectory's. Evaluation, the viewer and segs.track
read the run through this object.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from segs.data.frame import Sequence
from segs.map_points import MapPointLog
from segs.pipeline.sources import FrameSource
from segs.slam.base import MapUpdate


@dataclass
class Keyframe:
    """A keyframe handed over: its frame, its latest w2c [4,4] and whether the mapper trains on it."""

    frame_index: int
    w2c: np.ndarray
    trained: bool


@dataclass
class Routed:
    """One MapUpdate as the mapper receives it.

    views: (kf_id, frame index, w2c [4,4]) of the new training keyframes; poses: refreshed w2c of
    the other keyframes (held-out ones included, the mapper ignores ids it does not know);
    corrections: loop corrections (kf_id -> world-to-world [4,4]); points [M,3], colors [M,3],
    point_kf [M]: the new map points not created by a held-out keyframe.
    """

    views: list[tuple[int, int, np.ndarray]] = field(default_factory=list)
    poses: dict[int, np.ndarray] = field(default_factory=dict)
    corrections: dict[int, np.ndarray] = field(default_factory=dict)
    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    colors: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    point_kf: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))


class RunState:
    """The run of `sequence` tracked by `source`, split by `holdout_every` (0: no frame held out)."""

    def __init__(self, sequence: Sequence, source: FrameSource, holdout_every: int = 0):
        self.sequence, self.source, self.holdout_every = sequence, source, int(holdout_every)
        self.keyframes: dict[int, Keyframe] = {}
        self.held_out_points = 0  # SLAM points created by held-out keyframes, never given to the mapper
        self.map_points = MapPointLog()
        self.finished = False

    # -- what the frame source knows ---------------------------------------------------------------
    @property
    def mode(self) -> str:
        return self.source.mode

    @property
    def uses_ground_truth_poses(self) -> bool:
        return self.source.uses_ground_truth_poses

    def trajectory(self) -> dict[int, np.ndarray]:
        """frame index -> estimated w2c [4,4] of every tracked frame."""
        return self.source.trajectory()

    def lost_frames(self) -> list[int]:
        return self.source.lost_frames()

    def dropped_frames(self) -> list[int]:
        return self.source.dropped_frames()

    def keyframe_frames(self) -> dict[int, int]:
        """kf_id -> frame index of the frontend's keyframes still in its map."""
        return self.source.keyframe_frames()

    def tracking_fps(self) -> float | None:
        return self.source.tracking_fps()

    # -- the split and the registry ------------------------------------------------------------------
    def held_out(self, frame_index: int) -> bool:
        """Whether a keyframe of this frame is held out of training."""
        return bool(self.holdout_every and frame_index % self.holdout_every == 0)

    def trained_frames(self) -> dict[int, int]:
        """kf_id -> frame index of the keyframes the mapper trains on."""
        return {k: kf.frame_index for k, kf in self.keyframes.items() if kf.trained}

    def held_out_keyframes(self) -> list[int]:
        return [k for k, kf in self.keyframes.items() if not kf.trained]

    def test_frames(self) -> list[int]:
        """Tracked frames whose images were never trained on (the paper's test views)."""
        trained = set(self.trained_frames().values())
        return sorted(i for i in self.trajectory() if i not in trained)

    def route(self, update: MapUpdate) -> Routed | None:
        """Register the keyframes of `update`, split them, log its map points; -> what the mapper
        receives (None for an empty update). A new keyframe without a frame index or a pose is
        not handed over."""
        if update.is_empty():
            return None
        self.map_points.add(update)
        kf_frames = self.keyframe_frames()
        out = Routed(poses=dict(update.poses), corrections=update.corrections)
        for kf_id in update.new_keyframes:
            idx = kf_frames.get(kf_id)
            if idx is None or kf_id not in out.poses:
                continue
            trained = not self.held_out(idx)
            w2c = out.poses.pop(kf_id) if trained else out.poses[kf_id]
            self.keyframes[kf_id] = Keyframe(idx, w2c, trained)
            if trained:
                out.views.append((kf_id, idx, w2c))
        for kf_id, w2c in out.poses.items():
            if kf_id in self.keyframes:
                self.keyframes[kf_id].w2c = w2c
        keep = self._mappable_points(update.point_kf, kf_frames)
        if keep.any():
            out.points, out.colors, out.point_kf = update.points[keep], update.colors[keep], update.point_kf[keep]
        return out

    def _mappable_points(self, point_kf: np.ndarray, kf_frames: dict[int, int]) -> np.ndarray:
        """[M] bool: points not created by a held-out keyframe (their depth / colour come from a
        test frame, which the map must not see); the others are counted in held_out_points."""
        held = set(self.held_out_keyframes())
        if self.holdout_every:
            held |= {k for k, i in kf_frames.items() if i % self.holdout_every == 0}
        keep = ~np.isin(np.asarray(point_kf, dtype=np.int64), np.fromiter(held, np.int64, len(held)))
        self.held_out_points += int((~keep).sum())
        return keep

    def finish(self) -> MapUpdate:
        """End of the sequence: the frontend's final update, with every keyframe's pose replaced by
        the final trajectory's."""
        self.finished = True
        update = self.source.finish()
        traj = self.trajectory()
        for kf_id, idx in self.keyframe_frames().items():
            if idx in traj:
                update.poses.setdefault(kf_id, traj[idx])
        return update

    def write_partial_trajectory(self, path) -> None:
        """The estimated trajectory so far (TUM format), e.g. when training is interrupted."""
        from segs.trajectory import estimated_c2w, write_tum

        idx, c2w = estimated_c2w(self.trajectory())
        write_tum(path, self.sequence.timestamps[idx], c2w)

    # -- checkpoints ------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        """The source (with its frontend), the registry (arrays), the counters and the map points."""
        ids = sorted(self.keyframes)
        kfs = [self.keyframes[k] for k in ids]
        return {
            "source": self.source.state_dict(),
            "keyframes": {"kf_id": np.array(ids, np.int64), "frame_index": np.array([k.frame_index for k in kfs], np.int64),
                          "w2c": np.array([k.w2c for k in kfs], np.float64).reshape(-1, 4, 4),
                          "trained": np.array([k.trained for k in kfs], bool)},  # fmt: skip
            "held_out_points": self.held_out_points,
            "finished": self.finished,
            "map_points": self.map_points.state_dict(),
        }

    def load_state_dict(self, state: dict) -> None:
        self.source.load_state_dict(state["source"])
        kf = state["keyframes"]
        self.keyframes = {int(k): Keyframe(int(i), np.asarray(w, np.float64), bool(t))
                          for k, i, w, t in zip(kf["kf_id"], kf["frame_index"], kf["w2c"], kf["trained"])}  # fmt: skip
        self.held_out_points, self.finished = int(state["held_out_points"]), bool(state["finished"])
        self.map_points.load_state_dict(state["map_points"])
