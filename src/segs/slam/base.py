"""The frontend interface: what any tracker (ground truth or ORB-SLAM style) gives the mapper.

Poses are world-to-camera 4x4 float64 matrices (w2c). Nothing here knows about training.
"""
from __future__ import annotations

import abc
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from segs.data.frame import Frame

# the one version of segs's checkpoint state (the bridge's run state, the frame source, the
# frontends): plain arrays, numbers and containers, no pickled class instance. Earlier states
# ("segs.orb.v1", "segs.orb.v2", "segs.process.v1", the bridge's before v3) are converted when
# loaded (segs.slam.orb_state, segs.pipeline.legacy).
STATE_FORMAT = "segs.state.v3"


@dataclass
class FrameResult:
    """Outcome of tracking one frame: w2c [4,4] or None when lost; kf_id when it became a keyframe."""

    frame_index: int
    w2c: np.ndarray | None
    kf_id: int | None = None

    @property
    def tracked(self) -> bool:
        return self.w2c is not None


def _empty_points() -> np.ndarray:
    return np.zeros((0, 3), np.float64)


@dataclass
class MapUpdate:
    """Everything the mapper must learn since the previous poll.

    new_keyframes: kf ids created since the last poll (their frame: Frontend.keyframe_frames()).
    poses:         kf_id -> w2c [4,4] for new keyframes and keyframes whose pose was refined.
    points:        [M,3] float64 world positions of map points that appear for the first time.
    colors:        [M,3] float32 in [0,1] (image colour at the creating keyframe's keypoint).
    point_kf:      [M] int64 kf_id of the keyframe that created each point.
    corrections:   kf_id -> world-to-world similarity [4,4] (c2w_new @ w2c_old) applied by a
                   loop closure; the structure created by that keyframe moves with it.
    """

    new_keyframes: list[int] = field(default_factory=list)
    poses: dict[int, np.ndarray] = field(default_factory=dict)
    points: np.ndarray = field(default_factory=_empty_points)
    colors: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    point_kf: np.ndarray = field(default_factory=lambda: np.zeros((0,), np.int64))
    corrections: dict[int, np.ndarray] = field(default_factory=dict)

    def is_empty(self) -> bool:
        return not (self.new_keyframes or self.poses or len(self.points) or self.corrections)

    def state_dict(self) -> dict:
        """The update as arrays (checkpoints): dict orders kept."""
        return {"new_keyframes": np.array(self.new_keyframes, np.int64), "poses": _pose_dict(self.poses),
                "points": self.points, "colors": self.colors, "point_kf": self.point_kf,
                "corrections": _pose_dict(self.corrections)}  # fmt: skip

    @classmethod
    def from_state(cls, state: dict) -> "MapUpdate":
        return cls(new_keyframes=state["new_keyframes"].tolist(), poses=_pose_dict_from(state["poses"]),
                   points=state["points"], colors=state["colors"], point_kf=state["point_kf"],
                   corrections=_pose_dict_from(state["corrections"]))  # fmt: skip

    def merge(self, other: "MapUpdate") -> "MapUpdate":
        """Return self followed by other (later poses and corrections win / compose)."""
        corrections = dict(self.corrections)
        for k, t in other.corrections.items():
            corrections[k] = t @ corrections[k] if k in corrections else t
        return MapUpdate(
            new_keyframes=self.new_keyframes + [k for k in other.new_keyframes if k not in self.new_keyframes],
            poses={**self.poses, **other.poses},
            points=np.concatenate([self.points, other.points]),
            colors=np.concatenate([self.colors, other.colors]),
            point_kf=np.concatenate([self.point_kf, other.point_kf]),
            corrections=corrections,
        )


def _pose_dict(poses: dict[int, np.ndarray]) -> dict:
    """kf_id -> [4,4] as {"kf_id": [K], "T": [K,4,4]} in dict order."""
    return {"kf_id": np.array(list(poses), np.int64), "T": np.array(list(poses.values()), np.float64).reshape(-1, 4, 4)}


def _pose_dict_from(state: dict) -> dict[int, np.ndarray]:
    return {k: T.copy() for k, T in zip(state["kf_id"].tolist(), state["T"])}


class Frontend(abc.ABC):
    """A tracker that turns a frame stream into keyframes, poses and structure.

    uses_ground_truth_poses: the poses it reports are the dataset's own (slam=known_poses), so
    there is no trajectory estimate to score: ATE is n/a, never 0.
    """

    uses_ground_truth_poses: bool = False

    @abc.abstractmethod
    def process(self, frame: Frame) -> FrameResult:
        """Track one frame, raw or as prepare() returned it (in single-thread mode this also runs
        local mapping)."""

    def prepare(self, frame: Frame) -> Frame:
        """Per-frame work that needs nothing of the map (feature extraction), so that a frame
        source can run it ahead in another thread while the previous frame is tracked;
        process() accepts what this returns as well as the raw frame. Default: the frame."""
        return frame

    def preparer(self) -> Callable[[Frame], Any] | None:
        """A picklable callable doing what prepare() does, for a frame reader in a process of its
        own (no interpreter lock shared with tracking); None: prepare() runs in this process only."""
        return None

    @abc.abstractmethod
    def poll(self) -> MapUpdate:
        """Everything new since the previous poll (empty MapUpdate if nothing)."""

    @abc.abstractmethod
    def finish(self) -> MapUpdate:
        """End of the sequence: final optimisation; returns the resulting update."""

    @abc.abstractmethod
    def trajectory(self) -> dict[int, np.ndarray]:
        """frame index -> estimated w2c [4,4] of every tracked frame, with the latest keyframe poses."""

    @abc.abstractmethod
    def lost_frames(self) -> list[int]:
        """Frame indices that could not be tracked (never invented poses)."""

    @abc.abstractmethod
    def keyframe_frames(self) -> dict[int, int]:
        """kf_id -> frame index of every keyframe still in the map."""

    def state_dict(self) -> dict:
        """Checkpoint state (override to support resume): {"format": STATE_FORMAT, "kind": ...}
        with plain numbers, strings, arrays and containers only."""
        raise NotImplementedError(f"{type(self).__name__} does not support checkpointing")

    def load_state_dict(self, state: dict) -> None:
        raise NotImplementedError(f"{type(self).__name__} does not support checkpointing")


def prepared_seconds(frame) -> float:
    """Wall seconds Frontend.prepare spent on a prepared frame (0 for a raw one)."""
    return float(getattr(frame, "build_seconds", (0.0, 0.0))[0])
