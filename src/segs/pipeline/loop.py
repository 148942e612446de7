"""The one frame loop of segs: a reader's frames, in order, each tracked by `Frontend.process`.

segs.track, segs.train (through its frame source) and the child process of slam_mode=process |
live all track their frames here; they differ only in the reader (segs.pipeline.readers) and in
when they poll the frontend's MapUpdate.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Iterator

from segs.pipeline.readers import Read
from segs.slam.base import FrameResult, Frontend, MapUpdate, prepared_seconds


@dataclass
class Tracked:
    """One frame through the loop: the reader's frame, the frontend's result, the frame's cost
    (process() plus the features a reader prepared ahead) and the frames dropped before it."""

    frame: Any
    result: FrameResult
    seconds: float
    dropped: list[int]


class FrameLoop:
    """`frontend` fed with the frames of `reads` (an iterator of segs.pipeline.readers.Read).

    frames_done / process_seconds count the frames tracked and their cost, finish_seconds the
    time in finish(); a frame source restores them when a run resumes.
    """

    def __init__(self, frontend: Frontend, reads: Iterator[Read]):
        self.frontend, self._reads = frontend, reads
        self.frames_done, self.process_seconds, self.finish_seconds = 0, 0.0, 0.0

    def step(self) -> Tracked | None:
        """Track the next frame (None when the reader has none left); the frontend is not polled."""
        read = next(self._reads, None)
        if read is None:
            return None
        frame, item, dropped = read
        t0 = time.perf_counter()
        result = self.frontend.process(item)
        # the frame's own cost: tracking plus the features a reader built ahead (their wall time,
        # kept on the prepared frame), as when process() builds them
        seconds = time.perf_counter() - t0 + prepared_seconds(item)
        self.process_seconds += seconds
        self.frames_done += 1
        return Tracked(frame, result, seconds, dropped)

    def poll(self) -> MapUpdate:
        """Everything new since the previous poll."""
        return self.frontend.poll()

    def finish(self) -> MapUpdate:
        """End of the sequence: the frontend's final optimisation (timed); the reader is closed."""
        self.close()
        t0 = time.perf_counter()
        update = self.frontend.finish()
        self.finish_seconds += time.perf_counter() - t0
        return update

    def close(self) -> None:
        """Stop the reader (a reader thread or process ends here)."""
        close = getattr(self._reads, "close", None)
        if close is not None:
            close()
