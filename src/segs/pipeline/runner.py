"""Feeding a sequence to a frontend without training (tracking-only runs, benchmarks, tests)."""
from __future__ import annotations

import multiprocessing as mp
import pickle
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from queue import Empty
from typing import Any, Callable, Iterable, Iterator

from segs import process_settings
from segs.data.frame import Frame, Sequence
from segs.errors import ConfigError
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
                 prefetch: int = 0, reader: str = "thread",
                 on_update: Callable[[MapUpdate], None] | None = None) -> RunResult:
    """Process the frames (default: all) in order, polling after each, then finish().

    prefetch: frames read and prepared (`Frontend.prepare`: features) ahead while the current one
    is tracked; the results are the same, only the wall clock differs. process_s counts each
    frame's prepare time as well, so it stays the per-frame cost. reader: where they are read,
    "thread" (a background thread of this process) or "process" (a child process, which shares no
    interpreter lock with tracking; needs `Frontend.preparer()`, else a thread is used). With a
    process reader on_frame gets the prepared frame (index, timestamp, features), not the images.
    on_update: called with each polled MapUpdate (finish's included), in order.
    """
    if reader not in ("thread", "process"):
        raise ConfigError(f"run_sequence: reader must be 'thread' or 'process', got {reader!r}")
    out = RunResult()
    indices = range(len(sequence)) if frames is None else frames
    preparer = frontend.preparer() if reader == "process" and prefetch > 0 else None
    source = (_frames_in_process(preparer, sequence, list(indices), prefetch) if preparer is not None
              else _frames(frontend, sequence, indices, prefetch))
    for frame, item in source:
        t0 = time.perf_counter()
        res = frontend.process(item)
        out.process_s += time.perf_counter() - t0 + prepared_seconds(item)
        out.results.append(res)
        update = frontend.poll()
        out.update = out.update.merge(update)
        if on_update is not None:
            on_update(update)
        if on_frame is not None:
            on_frame(frame, res)
    t0 = time.perf_counter()
    update = frontend.finish()
    out.finish_s = time.perf_counter() - t0
    out.update = out.update.merge(update)
    if on_update is not None:
        on_update(update)
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


def _frames_in_process(preparer: Callable[[Frame], Any], sequence: Sequence, indices: list[int],
                       ahead: int) -> Iterator[tuple[Any, Any]]:
    """(prepared frame, prepared frame) in order, read and prepared by a child process that stays
    up to `ahead` frames in front."""
    for item in iterate_in_process(_prepare_each, (preparer, sequence, indices), ahead):
        yield item, item


def _prepare_each(preparer: Callable[[Frame], Any], sequence: Sequence, indices: list[int]) -> Iterator[Any]:
    for i in indices:
        yield preparer(sequence[i])


def iterate_in_process(produce: Callable[..., Iterator[Any]], args: tuple, ahead: int = 0) -> Iterator[Any]:
    """The items of produce(*args), computed in a spawned child process (produce and args must
    pickle) and yielded here in order; ahead > 0: at most that many wait in the queue (the child
    blocks), 0: no bound. An error in the child is raised here; leaving the loop early (an
    exception, Ctrl-C, close()) stops the child."""
    ctx = mp.get_context("spawn")  # not fork: this process may hold threads and OpenMP / OpenCV pools
    work, items = ctx.Queue(), ctx.Queue(maxsize=max(int(ahead), 0))
    child = ctx.Process(target=_produce_into, args=(work, items), name="segs-frames", daemon=True)
    child.start()
    # the work goes through a queue, not the start arguments: a child that dies while starting (a
    # script without a main guard) would leave a large argument write blocked for ever
    work.put((produce, args))
    try:
        while True:
            kind, item = _next_item(items, child)
            if kind == "end":
                return
            if kind == "error":
                raise item
            yield item
    finally:
        if child.is_alive():
            child.terminate()
        child.join()
        for q in (work, items):
            q.cancel_join_thread()
            q.close()


def _next_item(items, child) -> tuple[str, Any]:
    while True:
        try:
            return items.get(timeout=0.5)
        except Empty:
            if not child.is_alive() and items.empty():
                raise RuntimeError(f"the frame reader process ended (exit code {child.exitcode}) before "
                                   "sending every frame (at once: the script that starts it lacks an "
                                   "`if __name__ == '__main__':` guard)") from None


def _produce_into(work, items) -> None:
    """Child process: every item of produce(*args) into `items`, then ("end", None); an error goes
    there as ("error", e)."""
    process_settings.apply()  # a spawned process: nothing of its parent's allocator settings
    try:
        produce, args = work.get()
        for item in produce(*args):
            items.put(("item", item))
        items.put(("end", None))
    except BaseException as e:  # noqa: BLE001 - every failure is reported to the parent
        try:
            pickle.dumps(e)
        except Exception:  # noqa: BLE001
            e = RuntimeError(f"{type(e).__name__}: {e}")
        items.put(("error", e))
