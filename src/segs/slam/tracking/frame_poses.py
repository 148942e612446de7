"""The per-frame pose record of the ORB frontend: each tracked frame's pose relative to a keyframe.

Tracking writes it (one `FramePoses`, owned by the `Tracker`); the frontend reads it for
`trajectory()`, `lost_frames()` and `keyframe_frames()`. A frame's pose is kept relative to its
reference keyframe, so that it follows the keyframe when bundle adjustment or a loop closure moves
it (ORB-SLAM's mlRelativeFramePoses).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Iterable

import numpy as np

from segs.slam.geometry import inv_se3

KeyFramePose = Callable[[int], "np.ndarray | None"]  # kf_id -> w2c [4,4] (Map.kf_pose), None if unknown


@dataclass
class FramePose:
    """One tracked frame: keyframe `kf_id` itself (rel None), `rel` [4,4] = w2c @ inv(w2c of kf_id),
    or, without a reference keyframe (kf_id None), the absolute `w2c` [4,4]."""

    kf_id: int | None
    rel: np.ndarray | None = None
    w2c: np.ndarray | None = None

    def resolve(self, kf_pose: KeyFramePose) -> np.ndarray | None:
        """The frame's w2c [4,4] with the keyframes' current poses; None if its keyframe is gone."""
        if self.kf_id is None:
            return self.w2c.copy()
        base = kf_pose(self.kf_id)
        if base is None:
            return None
        return base.copy() if self.rel is None else self.rel @ base

    @classmethod
    def from_legacy(cls, rec: tuple) -> "FramePose":
        """The tuple form of checkpoints "segs.orb.v1": ("kf", id), ("rel", id, rel), ("abs", None, w2c)."""
        if rec[0] == "kf":
            return cls(rec[1])
        if rec[0] == "rel":
            return cls(rec[1], rel=rec[2])
        return cls(None, w2c=rec[2])


@dataclass
class FramePoses:
    """frame index -> FramePose of the tracked frames, the frames reported lost, and the frame
    index of every keyframe ever made (kf_id -> frame index)."""

    poses: dict[int, FramePose] = field(default_factory=dict)
    lost: set[int] = field(default_factory=set)
    kf_frames: dict[int, int] = field(default_factory=dict)

    def record(self, frame_index: int, w2c: np.ndarray | None, kf_id: int | None, ref_kf: int | None,
               kf_pose: KeyFramePose) -> None:
        """A frame as tracking left it: lost (w2c None), keyframe kf_id, or relative to ref_kf."""
        if w2c is None:
            self.lost.add(frame_index)
        elif kf_id is not None:
            self.poses[frame_index] = FramePose(kf_id)
            self.kf_frames[kf_id] = frame_index
        else:
            base = kf_pose(ref_kf) if ref_kf is not None else None
            if base is None:  # no reference keyframe (cannot happen after initialization)
                self.poses[frame_index] = FramePose(None, w2c=w2c.copy())
            else:
                self.poses[frame_index] = FramePose(ref_kf, rel=w2c @ inv_se3(base))

    def add_keyframe(self, frame_index: int, kf_id: int) -> None:
        """A frame reported lost that became keyframe kf_id afterwards (monocular initialization)."""
        self.poses[frame_index] = FramePose(kf_id)
        self.kf_frames[kf_id] = frame_index
        self.lost.discard(frame_index)

    def add_relative(self, frame_index: int, kf_id: int, rel: np.ndarray) -> None:
        """A frame reported lost, tracked afterwards: w2c = rel [4,4] @ w2c of keyframe kf_id."""
        self.poses[frame_index] = FramePose(kf_id, rel=rel.copy())
        self.lost.discard(frame_index)

    def w2c(self, frame_index: int, kf_pose: KeyFramePose) -> np.ndarray | None:
        """Current w2c [4,4] of a frame that has a reference keyframe, else None."""
        rec = self.poses.get(frame_index)
        return None if rec is None or rec.kf_id is None else rec.resolve(kf_pose)

    def trajectory(self, kf_pose: KeyFramePose) -> dict[int, np.ndarray]:
        """frame index -> w2c [4,4] of every tracked frame whose keyframe is still known."""
        out = {}
        for idx, rec in sorted(self.poses.items()):
            w2c = rec.resolve(kf_pose)
            if w2c is not None:
                out[idx] = w2c
        return out

    def lost_frames(self) -> list[int]:
        return sorted(self.lost - set(self.poses))

    def keyframe_frames(self, live: Iterable[int]) -> dict[int, int]:
        """kf_id -> frame index of the keyframes `live` (sorted ids)."""
        return {k: self.kf_frames[k] for k in sorted(live) if k in self.kf_frames}

    def __len__(self) -> int:
        return len(self.poses)

    @classmethod
    def from_legacy(cls, traj: dict[int, tuple], lost: set[int], kf_frames: dict[int, int]) -> "FramePoses":
        """The record of a "segs.orb.v1" checkpoint (`_traj` tuples, `_lost`, `_kf_frames`)."""
        return cls({i: FramePose.from_legacy(r) for i, r in traj.items()}, set(lost), dict(kf_frames))
