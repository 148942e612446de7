"""Frame readers: a sequence's frames, in order, as the frame loop (segs.pipeline.loop) takes them.

Every reader yields `Read` triples (the frame as the caller sees it, what `Frontend.process`
gets, the frames dropped before it):

- `on_demand`: each frame read when the loop asks for it (segs.train's interleaved mode);
- `ahead_in_thread` / `ahead_in_process`: read and prepared (`Frontend.prepare`: features) up to
  `ahead` frames in front of tracking, in a thread or in a spawned process that shares no
  interpreter lock with tracking (segs.track, the child process);
- `CameraFrames`: the child process's reader, every frame ("process") or, like a camera, the
  newest one at the frames' timestamps ("live": frames whose time passed are dropped).
"""
from __future__ import annotations

import multiprocessing as mp
import pickle
import threading
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from queue import Empty
from typing import Any, Callable, Iterable, Iterator

import numpy as np

from segs import process_settings
from segs.data.frame import Frame, Sequence
from segs.errors import ConfigError

Read = tuple[Any, Any, list[int]]  # (frame for the caller, what process() gets, frames dropped before it)
READERS = ("thread", "process")


def open_reader(prepare: Callable[[Frame], Any], preparer: Callable[[Frame], Any] | None, sequence: Sequence,
                indices: list[int], ahead: int, reader: str) -> Iterator[Read]:  # fmt: skip
    """The reader of `indices`: on demand (ahead <= 0), else `ahead` frames in front, prepared by
    `prepare` in a thread, or by the picklable `preparer` in a process (reader "process"; a
    thread where there is no preparer). Lazy: nothing is read before the first frame is asked for."""
    if reader not in READERS:
        raise ConfigError(f"run_sequence: reader must be 'thread' or 'process', got {reader!r}")
    if ahead <= 0:
        return on_demand(sequence, indices)
    if reader == "process" and preparer is not None:
        return ahead_in_process(preparer, sequence, indices, ahead)
    return ahead_in_thread(prepare, sequence, indices, ahead)


def on_demand(sequence: Sequence, indices: Iterable[int]) -> Iterator[Read]:
    """Each frame read when it is asked for."""
    for i in indices:
        frame = sequence[i]
        yield frame, frame, []


def ahead_in_thread(prepare: Callable[[Frame], Any], sequence: Sequence, indices: Iterable[int],
                    ahead: int) -> Iterator[Read]:  # fmt: skip
    """(raw frame, prepared frame, []) in order, read and prepared by a thread that stays up to
    `ahead` frames in front."""

    def load(i: int) -> Read:
        frame = sequence[i]
        return frame, prepare(frame), []

    it = iter(indices)
    with ThreadPoolExecutor(1, thread_name_prefix="segs-frames") as pool:
        pending = deque(pool.submit(load, i) for _, i in zip(range(ahead), it))
        while pending:
            done = pending.popleft()
            nxt = next(it, None)
            if nxt is not None:
                pending.append(pool.submit(load, nxt))
            yield done.result()


def ahead_in_process(preparer: Callable[[Frame], Any], sequence: Sequence, indices: list[int],
                     ahead: int) -> Iterator[Read]:  # fmt: skip
    """(prepared frame, prepared frame, []) in order, read and prepared by a child process that
    stays up to `ahead` frames in front (the caller sees the prepared frame: no images)."""
    for item in iterate_in_process(_prepare_each, (preparer, sequence, list(indices)), ahead):
        yield item, item, []


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


# ---------------------------------------------------------------------- a camera's frames
def next_live(timestamps: np.ndarray, i: int, t0: float, ts0: float, rate: float) -> tuple[int, list[int]]:
    """Live pacing: wait for frame i's time; if later frames' times have passed already, the
    newest of them is due and the ones before it are dropped. -> (frame due, dropped)."""
    now = (time.perf_counter() - t0) * rate + ts0
    if timestamps[i] > now:
        time.sleep((timestamps[i] - now) / rate)
        return i, []
    newest = int(np.searchsorted(timestamps, now, side="right")) - 1
    newest = max(i, min(newest, len(timestamps) - 1))
    return newest, list(range(i, newest))


def _read_frames(sequence: Sequence, prepare: Callable[[Frame], Any], timestamps: np.ndarray, start: int,
                 live: bool, rate: float, stopped: Callable[[], bool] = lambda: False) -> Iterator[tuple[Any, list[int]]]:
    """(prepared frame, frames dropped before it) from `start` on: every frame, or live the newest
    at rate x the wall clock since the first."""
    n, i = len(sequence), start
    t0 = time.perf_counter()
    ts0 = float(timestamps[i]) if i < n else 0.0
    while i < n and not stopped():
        dropped: list[int] = []
        if live:
            i, dropped = next_live(timestamps, i, t0, ts0, rate)
        yield prepare(sequence[i]), dropped
        i += 1


class CameraFrames:
    """The child process's frames, read (decoded, depth registered) and prepared (the frontend's
    `prepare`: feature extraction) ahead of the tracking of the previous frame: in a process of
    their own when the frontend has a picklable `preparer` (no interpreter lock shared with
    tracking), else in a background thread (OpenCV's decoders and ORB release the GIL).

    process: every frame in order, up to `ahead` read in advance. live: a camera; frame i is read
    at its time (rate x wall clock) into a one-frame slot; a frame still in the slot when the next
    arrives, or whose time passed before it could be read, is dropped (the tracker always gets
    the newest image, as from a live driver). Iterating yields `Read`s; `tail_dropped` holds the
    frames dropped after the last one.
    """

    def __init__(self, sequence: Sequence, start: int, live: bool, rate: float, ahead: int = 4,
                 prepare: Callable[[Frame], Any] = lambda frame: frame,
                 preparer: Callable[[Frame], Any] | None = None):
        self.sequence, self.live, self.rate, self.prepare = sequence, live, rate, prepare
        self.timestamps = np.asarray(sequence.timestamps, np.float64)
        self._cv = threading.Condition()
        self._frames: list[Frame] = []
        self._dropped: list[int] = []
        self._ended = False
        self._error: BaseException | None = None
        self._ahead = 1 if live else ahead
        self._stop = False
        self.tail_dropped: list[int] = []
        if preparer is not None:  # the reader process runs ahead by itself; the slot logic stays here
            frames = iterate_in_process(_read_frames, (sequence, preparer, self.timestamps, start, live, rate),
                                        0 if live else self._ahead)
        else:
            frames = _read_frames(sequence, prepare, self.timestamps, start, live, rate, lambda: self._stop)
        threading.Thread(target=self._deliver, args=(frames,), name="segs-frames", daemon=True).start()

    def _deliver(self, frames: Iterator[tuple[Any, list[int]]]) -> None:
        try:
            for frame, dropped in frames:
                with self._cv:
                    self._dropped.extend(dropped)
                    if self.live and self._frames:  # the tracker did not take the previous one
                        self._dropped.extend(f.index for f in self._frames)
                        self._frames.clear()
                    while not self.live and len(self._frames) >= self._ahead and not self._stop:
                        self._cv.wait()
                    if self._stop:
                        break
                    self._frames.append(frame)
                    self._cv.notify_all()
        except BaseException as exc:  # raised in the tracker's thread by next()
            self._error = exc
        finally:
            close = getattr(frames, "close", None)
            if close is not None:
                close()  # a reader process stops here
        with self._cv:
            self._ended = True
            self._cv.notify_all()

    def next(self) -> tuple[Any, list[int]]:
        """The next frame to track, as prepared (None after the last), and the frames dropped
        before it."""
        with self._cv:
            while not self._frames and not self._ended:
                self._cv.wait()
            if self._error is not None:
                raise self._error
            frame = self._frames.pop(0) if self._frames else None
            dropped, self._dropped = self._dropped, []
            self._cv.notify_all()
        return frame, dropped

    def __iter__(self) -> Iterator[Read]:
        while True:
            frame, dropped = self.next()
            if frame is None:
                self.tail_dropped = dropped
                return
            yield frame, frame, dropped

    def stop(self) -> None:
        with self._cv:
            self._stop = True
            self._cv.notify_all()
