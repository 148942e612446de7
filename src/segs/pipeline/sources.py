"""Frame sources: where a run's tracked frames and MapUpdates come from.

A `FrameSource` is a frontend fed with a sequence's frames through the frame loop
(segs.pipeline.loop), seen from the side that consumes its results (segs.track, segs.train's
bridge callback): `track()` advances it and returns the MapUpdate since the previous call,
`finish()` ends the sequence, and it answers for the trajectory, lost / dropped frames and
keyframes. Three implementations, one per `slam_mode`:

- `InterleavedSource` (here): the frontend runs in this process, `track(n)` tracks n more frames;
  the caller paces the camera (segs.train spreads the frames over training steps);
- `ProcessSource` and `LiveSource` (segs.pipeline.process): the frontend runs in a child process
  at its own pace (every frame, or a camera's frames at their timestamps); `track()` takes what
  the child reported meanwhile.
"""
from __future__ import annotations

import abc
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable

import numpy as np

from segs.data.frame import Sequence
from segs.errors import ConfigError
from segs.pipeline.loop import FrameLoop
from segs.pipeline.readers import open_reader
from segs.slam.base import FrameResult, Frontend, MapUpdate

OnFrame = Callable[[Any, FrameResult], None]  # (the reader's frame, its result), after each frame tracked here


class FrameSource(abc.ABC):
    """A frontend tracking `sequence`, as a run consumes it (see the module docstring).

    mode: its slam_mode; paced: whether track(frames) decides how many frames are tracked (the
    caller paces the camera) or the frontend runs at its own pace; on_frame: called after each
    frame tracked in this process (paced sources only); cursor: the next frame the frontend
    will see; frames_done / process_seconds: frames tracked and their cost (the tracking speed);
    finish_seconds: time in the frontend's finish() measured here.
    """

    mode: str
    paced: bool
    uses_ground_truth_poses: bool = False

    def __init__(self, sequence: Sequence):
        self.sequence = sequence
        self.on_frame: OnFrame | None = None

    @property
    @abc.abstractmethod
    def cursor(self) -> int:
        """The next frame index the frontend will see (len(sequence) at the end)."""

    @abc.abstractmethod
    def track(self, frames: int = 1, timeout: float = 0.0) -> MapUpdate:
        """Advance: a paced source tracks up to `frames` more frames, then polls the frontend; an
        unpaced one returns what its frontend reported since the previous call, waiting up to
        `timeout` seconds for a first report. Returns the MapUpdate since the previous call."""

    @abc.abstractmethod
    def exhausted(self) -> bool:
        """Every frame has been tracked (a child process: and its frontend has finished)."""

    @abc.abstractmethod
    def finish(self) -> MapUpdate:
        """End of the sequence: the frontend's final optimisation; returns everything not returned yet."""

    @abc.abstractmethod
    def trajectory(self) -> dict[int, np.ndarray]:
        """frame index -> w2c [4,4] of every tracked frame (the final poses after finish)."""

    @abc.abstractmethod
    def lost_frames(self) -> list[int]:
        """Frames the frontend could not track."""

    @abc.abstractmethod
    def keyframe_frames(self) -> dict[int, int]:
        """kf_id -> frame index of the frontend's keyframes still in its map."""

    def dropped_frames(self) -> list[int]:
        """Frames never tracked because the frontend was behind a live camera."""
        return []

    @property
    @abc.abstractmethod
    def frames_done(self) -> int: ...

    @property
    @abc.abstractmethod
    def process_seconds(self) -> float: ...

    @property
    def finish_seconds(self) -> float:
        return 0.0

    def remaining(self) -> int:
        """Frames of the sequence the frontend has not seen yet."""
        return max(len(self.sequence) - self.cursor, 0)

    def tracking_fps(self) -> float | None:
        """Frames per second of Frontend.process (tracking and, single-threaded, local mapping)."""
        return self.frames_done / self.process_seconds if self.process_seconds > 0 else None

    def stats(self) -> dict[str, Any]:
        """The frontend's own statistics."""
        return {}

    @abc.abstractmethod
    def state_dict(self) -> dict:
        """Checkpoint state: plain arrays, numbers and containers."""

    @abc.abstractmethod
    def load_state_dict(self, state: dict) -> None: ...

    def close(self) -> None:
        """Stop what the source started (a reader, a child process)."""

    def __enter__(self) -> "FrameSource":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class InterleavedSource(FrameSource):
    """`frontend` fed with the frames `frames` (default: all) of `sequence` in this process.

    ahead / reader: frames read and prepared (features) ahead of tracking, in a "thread" or a
    "process" (segs.pipeline.readers); ahead 0 reads each frame when it is tracked.
    """

    mode, paced = "interleaved", True

    def __init__(self, frontend: Frontend, sequence: Sequence, frames: Iterable[int] | None = None, ahead: int = 0,
                 reader: str = "thread"):  # fmt: skip
        super().__init__(sequence)
        self.frontend, self.ahead, self.reader = frontend, int(ahead), reader
        self.uses_ground_truth_poses = bool(frontend.uses_ground_truth_poses)
        self._indices = list(range(len(sequence))) if frames is None else [int(i) for i in frames]
        self._pos = 0
        self._loop = self._new_loop()

    def _new_loop(self) -> FrameLoop:
        """The frame loop from self._pos on (its reader starts with the first frame asked for)."""
        fe = self.frontend
        preparer = fe.preparer() if self.reader == "process" and self.ahead > 0 else None
        reads = open_reader(fe.prepare, preparer, self.sequence, self._indices[self._pos:], self.ahead, self.reader)
        return FrameLoop(fe, reads)

    @property
    def cursor(self) -> int:
        if self._pos < len(self._indices):
            return self._indices[self._pos]
        return self._indices[-1] + 1 if self._indices else 0

    @property
    def frames_done(self) -> int:
        return self._loop.frames_done

    @property
    def process_seconds(self) -> float:
        return self._loop.process_seconds

    @property
    def finish_seconds(self) -> float:
        return self._loop.finish_seconds

    def remaining(self) -> int:
        return len(self._indices) - self._pos

    def track(self, frames: int = 1, timeout: float = 0.0) -> MapUpdate:
        for _ in range(frames):
            if self.exhausted():
                break
            tracked = self._loop.step()
            self._pos += 1
            if self.on_frame is not None:
                self.on_frame(tracked.frame, tracked.result)
        return self._loop.poll()

    def exhausted(self) -> bool:
        return self._pos >= len(self._indices)

    def finish(self) -> MapUpdate:
        return self._loop.finish()

    def trajectory(self) -> dict[int, np.ndarray]:
        return self.frontend.trajectory()

    def lost_frames(self) -> list[int]:
        return self.frontend.lost_frames()

    def keyframe_frames(self) -> dict[int, int]:
        return self.frontend.keyframe_frames()

    def stats(self) -> dict[str, Any]:
        return self.frontend.stats() if hasattr(self.frontend, "stats") else {}

    def state_dict(self) -> dict:
        return {"mode": self.mode, "cursor": self.cursor, "frames_done": self.frames_done,
                "process_seconds": self.process_seconds, "frontend": self.frontend.state_dict()}  # fmt: skip

    def load_state_dict(self, state: dict) -> None:
        if state.get("mode") != self.mode:
            raise ConfigError(f"slam: the checkpoint's frontend ran with slam_mode={state.get('mode')}, this run "
                              f"with slam_mode={self.mode}; resume with the same slam_mode")  # fmt: skip
        self._loop.close()
        self.frontend.load_state_dict(state["frontend"])
        cursor = int(state["cursor"])
        self._pos = next((p for p, i in enumerate(self._indices) if i >= cursor), len(self._indices))
        self._loop = self._new_loop()
        self._loop.frames_done, self._loop.process_seconds = int(state["frames_done"]), float(state["process_seconds"])

    def close(self) -> None:
        self._loop.close()


@dataclass
class RunResult:
    """results: one FrameResult per fed frame; update: everything polled (finish included);
    process_s: seconds spent in frontend.process; finish_s: in frontend.finish."""

    results: list[FrameResult] = field(default_factory=list)
    update: MapUpdate = field(default_factory=MapUpdate)
    process_s: float = 0.0
    finish_s: float = 0.0


def run_sequence(frontend: Frontend, sequence: Sequence, frames: Iterable[int] | None = None,
                 on_frame: OnFrame | None = None, prefetch: int = 0, reader: str = "thread",
                 on_update: Callable[[MapUpdate], None] | None = None) -> RunResult:
    """Process the frames (default: all) in order, polling after each, then finish() (tests,
    benchmarks: an InterleavedSource driven to the end).

    prefetch: frames read and prepared (`Frontend.prepare`: features) ahead while the current one
    is tracked; the results are the same, only the wall clock differs. process_s counts each
    frame's prepare time as well, so it stays the per-frame cost. reader: where they are read,
    "thread" (a background thread of this process) or "process" (a child process, which shares no
    interpreter lock with tracking; needs `Frontend.preparer()`, else a thread is used). With a
    process reader on_frame gets the prepared frame (index, timestamp, features), not the images.
    on_update: called with each polled MapUpdate (finish's included), in order.
    """
    out = RunResult()
    fed: list[tuple[Any, FrameResult]] = []
    with InterleavedSource(frontend, sequence, frames, ahead=prefetch, reader=reader) as source:
        source.on_frame = lambda frame, res: fed.append((frame, res))
        while not source.exhausted():
            update = source.track(1)
            out.update = out.update.merge(update)
            if on_update is not None:
                on_update(update)
            for frame, res in fed:
                out.results.append(res)
                if on_frame is not None:
                    on_frame(frame, res)
            fed.clear()
        update = source.finish()
        out.update = out.update.merge(update)
        if on_update is not None:
            on_update(update)
        out.process_s, out.finish_s = source.process_seconds, source.finish_seconds
    return out
