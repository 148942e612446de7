"""Feeding a sequence to a frontend without training (tracking-only runs, benchmarks, tests)."""
from __future__ import annotations

import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Callable, Iterable, Iterator

from segs.data.frame import Frame, Sequence
from segs.slam.base import FrameResult, Frontend, MapUpdate, prepared_seconds


@dataclass
class RunResult:
    """results: one FrameResult per fed frame; update: everything polled (finish included);
    process_s: seconds spent in frontend.process; finish_s: in frontend.finish."""

    results: list[FrameResult] = field(default_factory=list)
    update: MapUpdate = field(default_factory=MapUpdate)
    process_s: float = 0.0
    finish_s: float = 0.0


def run_sequence(frontend: Frontend, sequence: Sequence, frames: Iterable[int] | None = None,
                 on_frame: Callable[[Frame, FrameResult], None] | None = None,
                 prefetch: int = 0) -> RunResult:
    """Process the frames (default: all) in order, polling after each, then finish().

    prefetch: frames read and prepared (`Frontend.prepare`: features) ahead in a background
    thread while the current one is tracked; the results are the same, only the wall clock
    differs. process_s counts each frame's prepare time as well, so it stays the per-frame cost.
    """
    out = RunResult()
    indices = range(len(sequence)) if frames is None else frames
    for frame, item in _frames(frontend, sequence, indices, prefetch):
        t0 = time.perf_counter()
        res = frontend.process(item)
        out.process_s += time.perf_counter() - t0 + prepared_seconds(item)
        out.results.append(res)
        out.update = out.update.merge(frontend.poll())
        if on_frame is not None:
            on_frame(frame, res)
    t0 = time.perf_counter()
    out.update = out.update.merge(frontend.finish())
    out.finish_s = time.perf_counter() - t0
    return out


def _frames(frontend: Frontend, sequence: Sequence, indices: Iterable[int],
            ahead: int) -> Iterator[tuple[Frame, Frame]]:
    """(frame, what process() gets) in order: the raw frame, or with ahead > 0 the frame as
    prepared by a reader thread that stays up to `ahead` frames in front."""
    if ahead <= 0:
        for i in indices:
            frame = sequence[i]
            yield frame, frame
        return

    def load(i: int) -> tuple[Frame, Frame]:
        frame = sequence[i]
        return frame, frontend.prepare(frame)

    it = iter(indices)
    with ThreadPoolExecutor(1, thread_name_prefix="segs-frames") as pool:
        pending = deque(pool.submit(load, i) for _, i in zip(range(ahead), it))
        while pending:
            done = pending.popleft()
            nxt = next(it, None)
            if nxt is not None:
                pending.append(pool.submit(load, nxt))
            yield done.result()
