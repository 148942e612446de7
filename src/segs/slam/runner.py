"""Feeding a sequence to a frontend without training (tracking-only runs, benchmarks, tests)."""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, Iterable

from segs.data.frame import Frame, Sequence
from segs.slam.base import FrameResult, Frontend, MapUpdate


@dataclass
class RunResult:
    """results: one FrameResult per fed frame; update: everything polled (finish included);
    process_s: seconds spent in frontend.process; finish_s: in frontend.finish."""

    results: list[FrameResult] = field(default_factory=list)
    update: MapUpdate = field(default_factory=MapUpdate)
    process_s: float = 0.0
    finish_s: float = 0.0


def run_sequence(frontend: Frontend, sequence: Sequence, frames: Iterable[int] | None = None,
                 on_frame: Callable[[Frame, FrameResult], None] | None = None) -> RunResult:
    """Process the frames (default: all) in order, polling after each, then finish()."""
    out = RunResult()
    for i in range(len(sequence)) if frames is None else frames:
        frame = sequence[i]
        t0 = time.perf_counter()
        res = frontend.process(frame)
        out.process_s += time.perf_counter() - t0
        out.results.append(res)
        out.update = out.update.merge(frontend.poll())
        if on_frame is not None:
            on_frame(frame, res)
    t0 = time.perf_counter()
    out.update = out.update.merge(frontend.finish())
    out.finish_s = time.perf_counter() - t0
    return out
