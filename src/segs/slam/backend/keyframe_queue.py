"""KeyFrameQueue: hands new keyframes from tracking to local mapping + loop closing.

Single-thread mode (deterministic): `submit` runs the work before it returns. Threaded mode: the
work runs in a background thread fed by a queue; an error there is raised in the caller's thread
at its next `submit` / `raise_error` / `stop`.
"""
from __future__ import annotations

import queue
import threading
from typing import Callable

from segs.slam.map.map import KeyFrame


class KeyFrameQueue:
    """work: what to do with each keyframe (local mapping, then loop closing); threaded: in a
    background thread; max_waiting: keyframes queued before `accepts_keyframes` says no."""

    def __init__(self, work: Callable[[KeyFrame], None], threaded: bool, max_waiting: int = 3):
        self.work, self.threaded, self.max_waiting = work, bool(threaded), max_waiting
        self._queue: queue.Queue | None = None
        self._worker: threading.Thread | None = None
        self._error: BaseException | None = None
        self._busy = False

    def submit(self, kf: KeyFrame) -> None:
        if not self.threaded:
            self.work(kf)
            return
        if self._worker is None:
            self._queue = queue.Queue()
            self._worker = threading.Thread(target=self._run, name="segs-orb-mapping", daemon=True)
            self._worker.start()
        self._queue.put(kf)

    def _run(self) -> None:
        while True:
            kf = self._queue.get()
            try:
                if kf is None:
                    return
                self._busy = True
                self.work(kf)
            except BaseException as e:  # surfaced in the caller's thread
                self._error = e
            finally:
                self._busy = False
                self._queue.task_done()

    def stop(self) -> None:
        """Wait for the queued keyframes, end the thread (restarted by the next submit)."""
        if self._worker is not None:
            self._queue.put(None)
            self._worker.join()
            self._worker = None
        self.raise_error()

    def raise_error(self) -> None:
        if self._error is not None:
            e, self._error = self._error, None
            raise RuntimeError("slam mapping thread failed") from e

    def accepts_keyframes(self) -> bool:
        """False while local mapping is behind (ORB-SLAM's AcceptKeyFrames)."""
        return not self.threaded or self._queue is None or self._queue.qsize() < self.max_waiting

    def idle(self) -> bool:
        """Nothing queued and nothing being mapped."""
        return not self.threaded or self._queue is None or (self._queue.empty() and not self._busy)
