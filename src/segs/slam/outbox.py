"""MapOutbox: what the ORB frontend has for the mapper since the last poll (one MapUpdate in the making).

Tracking, local mapping and loop closing put keyframes, poses, points and loop corrections in;
`OrbFrontend.poll` takes everything out. Thread-safe (its own lock): in threaded mode the mapping
thread writes while the caller's thread polls.
"""
from __future__ import annotations

import threading

import numpy as np

from segs.slam.base import MapUpdate


class MapOutbox:
    """Pending MapUpdate + point chunks (positions [M,3], colours [M,3], creating keyframe [M])."""

    def __init__(self, pending: MapUpdate | None = None, chunks: list[tuple] | None = None):
        self._pending = pending if pending is not None else MapUpdate()
        self._chunks: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = list(chunks or [])
        self._lock = threading.Lock()

    # the pickled form (checkpoints before segs.state.v3 pickled the outbox; converted when loaded)
    def __getstate__(self) -> dict:
        return {"pending": self._pending, "chunks": self._chunks}

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["pending"], state["chunks"])

    def state_dict(self) -> dict:
        """The pending update and point chunks as arrays (checkpoints)."""
        with self._lock:
            return {"pending": self._pending.state_dict(),
                    "chunks": [{"points": p, "colors": c, "point_kf": k} for p, c, k in self._chunks]}  # fmt: skip

    @classmethod
    def from_state(cls, state: dict) -> "MapOutbox":
        return cls(MapUpdate.from_state(state["pending"]), [(c["points"], c["colors"], c["point_kf"]) for c in state["chunks"]])

    def add_keyframe(self, kf_id: int, w2c: np.ndarray) -> None:
        """A keyframe for the mapper (announced once) with its w2c [4,4]."""
        with self._lock:
            if kf_id not in self._pending.new_keyframes:
                self._pending.new_keyframes.append(kf_id)
            self._pending.poses[kf_id] = w2c.copy()

    def add_poses(self, poses: dict[int, np.ndarray]) -> None:
        """Refreshed w2c [4,4] of keyframes (copied)."""
        with self._lock:
            for k, T in poses.items():
                self._pending.poses[k] = T.copy()

    def add_points(self, pos: np.ndarray, colors: np.ndarray, kf_ids: np.ndarray) -> None:
        """New map points: pos [M,3] float64, colors [M,3] float32, creating keyframe [M] int64."""
        with self._lock:
            self._chunks.append((pos, colors, kf_ids))

    def add_corrections(self, corr: dict[int, np.ndarray]) -> None:
        """Loop / global-BA corrections (kf_id -> world-to-world [4,4]); points not yet polled are
        moved now (an update is self-consistent: its points are already in the corrected world, its
        corrections concern earlier polls)."""
        with self._lock:
            self._pending = self._pending.merge(MapUpdate(corrections=corr))
            chunks = []
            for pos, col, kfs in self._chunks:
                pos = pos.copy()
                for k in np.unique(kfs).tolist():
                    T = corr.get(int(k))
                    if T is not None:
                        sel = kfs == k
                        pos[sel] = pos[sel] @ T[:3, :3].T + T[:3, 3]
                chunks.append((pos, col, kfs))
            self._chunks = chunks

    def take(self) -> MapUpdate:
        """Everything put in since the last take, as one MapUpdate; the outbox is empty afterwards."""
        with self._lock:
            up, self._pending = self._pending, MapUpdate()
            chunks, self._chunks = self._chunks, []
        if chunks:
            up.points, up.colors, up.point_kf = (np.concatenate([c[i] for c in chunks]) for i in range(3))
        return up
