"""The frontend in its own process: SLAM beside mapping, on another core.

gtsam and the ORB frontend's Python keep the GIL, so a tracking thread beside training slows
both; in a child process the frontend uses its own core and the mapper receives its MapUpdates
through a queue, as ORB-SLAM's tracking / local-mapping threads hand keyframes to a renderer.

`FrontendProcess` is a Frontend whose frames are read and tracked by the child, which owns the
sequence: the parent never calls process() (it raises); it starts the child, polls, and reads
trajectory / keyframes / lost frames from what the child reported. Two pacings:

- "process": every frame, as fast as the frontend tracks (deterministic in what it computes,
  only the moment updates arrive varies);
- "live": frames at their timestamps (wall clock from the first one, x `rate`), like a camera.
  When tracking falls behind, the frames whose time has passed are dropped and the newest one is
  tracked (a live camera driver delivers the latest image); they are counted in dropped_frames(),
  never invented poses.

The child is `python -m segs.pipeline.process` (pickles on stdin / stdout, like ba_process), so it
imports only the frontend's modules (no torch, no Lightning). Checkpoints: state_dict() asks the
child for its frontend state at a frame boundary and keeps every update the mapper has not
polled yet beside it, so a resumed run loses and repeats nothing.
"""
from __future__ import annotations

import os
import pickle
import queue
import subprocess
import sys
import threading
import time
from typing import Any, Callable, Iterator

import numpy as np

from segs import process_settings
from segs.data.frame import Frame, Sequence
from segs.errors import ConfigError
from segs.pipeline.runner import iterate_in_process
from segs.slam.base import FrameResult, Frontend, MapUpdate, prepared_seconds

MODES = ("interleaved", "process", "live")


class FrontendProcess(Frontend):
    """A frontend (built by make_frontend() in the child) tracking `sequence` in a child process.

    make_frontend: picklable callable -> Frontend (e.g. the slam config's partial with camera and
    sensor bound); mode: "process" | "live"; rate: live playback speed (1 = real time);
    uses_ground_truth_poses: what the frontend built by make_frontend says of itself.
    Call start() (or poll(), which starts it); finish() waits for the end of the sequence.
    """

    def __init__(self, make_frontend: Callable[[], Frontend], sequence: Sequence, mode: str = "process",
                 rate: float = 1.0, uses_ground_truth_poses: bool = False):
        if mode not in ("process", "live"):
            raise ConfigError(f"slam_mode={mode!r}: a frontend process runs in mode process or live")
        if not rate > 0:
            raise ConfigError(f"slam_rate={rate!r} must be > 0")
        self.make_frontend, self.sequence, self.mode, self.rate = make_frontend, sequence, mode, float(rate)
        self.uses_ground_truth_poses = bool(uses_ground_truth_poses)
        self._proc: subprocess.Popen | None = None
        self._inbox: queue.Queue = queue.Queue()  # messages read from the child, in order
        self._buffer: list[tuple] = []  # messages taken from the inbox, not yet given to poll()
        self._resume: dict | None = None
        self._reset()

    def _reset(self) -> None:
        self.cursor = 0  # next frame the child will read
        self._traj: dict[int, np.ndarray] = {}  # frame -> w2c as tracked (final poses after finish)
        self._lost: set[int] = set()
        self._dropped: list[int] = []
        self._kf_frames: dict[int, int] = {}
        self._final: dict | None = None  # the child's closing report
        self.process_seconds = 0.0  # seconds the child spent in frontend.process
        self.frames_done = 0
        self.wall_seconds = 0.0  # the child's time from its first frame to the end of finish()

    # ------------------------------------------------------------------ child control
    def start(self) -> None:
        """Start the child (once); it begins at self.cursor with the restored state, if any."""
        if self._proc is not None or self._final is not None:  # running, or the sequence is done
            return
        self._proc = subprocess.Popen([sys.executable, "-m", "segs.pipeline.process"], stdin=subprocess.PIPE,
                                      stdout=subprocess.PIPE)
        state = self._resume.get("frontend") if self._resume else None
        self._send(("start", self.make_frontend, self.sequence, self.mode, self.rate, self.cursor, state))
        threading.Thread(target=self._read, name="segs-frontend-reader", daemon=True).start()

    def _send(self, msg: tuple) -> None:
        try:
            pickle.dump(msg, self._proc.stdin, protocol=pickle.HIGHEST_PROTOCOL)
            self._proc.stdin.flush()
        except (BrokenPipeError, OSError):
            pass  # the child ended; its last message (error or done) says why

    def _read(self) -> None:
        out = self._proc.stdout
        while True:
            try:
                self._inbox.put(pickle.load(out))
            except (EOFError, OSError, pickle.UnpicklingError):
                self._inbox.put(("eof",))
                return

    def _next(self, block: bool, timeout: float | None = None) -> tuple | None:
        """One message from the child (None: nothing yet); errors and a dead child raise."""
        try:
            msg = self._inbox.get(block=block, timeout=timeout)
        except queue.Empty:
            return None
        if msg[0] == "error":
            raise RuntimeError(f"slam frontend process failed: {msg[1]}")
        if msg[0] == "eof":
            self._inbox.put(msg)  # every later read sees it too
            if self._final is None:
                raise RuntimeError("the slam frontend process ended unexpectedly")
            return None
        return msg

    def _apply(self, msg: tuple) -> MapUpdate:
        """Book-keeping of one frame / done message -> its MapUpdate."""
        if msg[0] == "frame":
            _, index, w2c, update, kf_frames, seconds, dropped = msg
            if w2c is None:
                self._lost.add(index)
            else:
                self._traj[index] = w2c
            self._kf_frames = kf_frames
            self._dropped.extend(dropped)
            self.process_seconds += seconds
            self.frames_done += 1
            self.cursor = index + 1
            return update
        if msg[0] == "done":
            _, update, report = msg
            self._final = report
            self._traj, self._lost = report["trajectory"], set(report["lost"])
            self._kf_frames, self.wall_seconds = report["keyframe_frames"], report["wall_s"]
            self._dropped.extend(report["dropped"])
            self.cursor = len(self.sequence)
            return update
        raise RuntimeError(f"unexpected message from the slam frontend process: {msg[0]!r}")

    # ------------------------------------------------------------------ Frontend API
    def process(self, frame: Frame) -> FrameResult:
        raise TypeError("FrontendProcess reads and tracks its frames in the child process; "
                        "call poll() / finish() instead of process()")

    def poll(self, timeout: float = 0.0) -> MapUpdate:
        """Everything the child reported since the previous poll; with a timeout > 0 and nothing
        reported yet, waits up to that many seconds for the first message."""
        self.start()
        up = MapUpdate()
        for msg in self._buffer:
            up = up.merge(self._apply(msg))
        if timeout > 0 and not self._buffer and not self.done():
            msg = self._next(block=True, timeout=timeout)
            if msg is not None:
                up = up.merge(self._apply(msg))
        self._buffer = []
        while (msg := self._next(block=False)) is not None:
            up = up.merge(self._apply(msg))
        return up

    def done(self) -> bool:
        """The child has tracked every frame and finished (its final update is polled)."""
        return self._final is not None

    def finish(self) -> MapUpdate:
        """Wait for the end of the sequence and the frontend's finish(); everything not polled."""
        up = self.poll()
        while not self.done():
            up = up.merge(self.poll(timeout=0.1))
        return up

    def trajectory(self) -> dict[int, np.ndarray]:
        """Tracked frames -> w2c: as tracked while running, the frontend's final poses after."""
        return {k: v.copy() for k, v in sorted(self._traj.items())}

    def lost_frames(self) -> list[int]:
        return sorted(self._lost - set(self._traj))

    def dropped_frames(self) -> list[int]:
        """Live mode: frames skipped because tracking was behind the camera (never tracked)."""
        return sorted(self._dropped)

    def keyframe_frames(self) -> dict[int, int]:
        return dict(self._kf_frames)

    def stats(self) -> dict[str, Any]:
        """The frontend's own statistics (after the end) and the process' figures."""
        out = dict(self._final["stats"]) if self._final else {}
        out.update(mode=self.mode, frames_dropped=len(self._dropped), child_process_s=self.process_seconds,
                   child_wall_s=self.wall_seconds)
        return out

    def close(self) -> None:
        """End the child (after finish it waits for this; before, it stops at the next frame)."""
        if self._proc is None:
            return
        self._send(("close",))
        try:
            self._proc.stdin.close()
        except OSError:
            pass
        try:
            self._proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self._proc.kill()
        self._proc = None

    def __del__(self) -> None:
        proc = getattr(self, "_proc", None)
        if proc is not None and proc.poll() is None:
            proc.kill()

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict:
        """The child's frontend state at a frame boundary, and every update not polled yet."""
        self.start()
        if self._proc is None:  # a resumed run whose sequence was already done
            inner = self._resume.get("frontend") if self._resume else None
        else:
            self._send(("state",))
            while (msg := self._next(block=True)) is not None and msg[0] != "state":
                self._buffer.append(msg)  # reported before the state: the mapper gets them later
            inner = msg[1] if msg is not None else None
        return {"format": "segs.process.v1", "frontend": inner, "pending": list(self._buffer),
                "cursor": self.cursor, "trajectory": dict(self._traj), "lost": sorted(self._lost),
                "dropped": list(self._dropped), "keyframe_frames": dict(self._kf_frames),
                "process_seconds": self.process_seconds, "frames_done": self.frames_done,
                "final": self._final}

    def load_state_dict(self, state: dict) -> None:
        if state.get("format") != "segs.process.v1":
            raise ConfigError("slam: checkpoint state is not a frontend-process state (was it saved with "
                              "slam_mode=interleaved?)")
        if self._proc is not None:
            raise RuntimeError("load_state_dict before the frontend process starts")
        self._reset()
        self._resume = state
        self._traj, self._lost = dict(state["trajectory"]), set(state["lost"])
        self._dropped, self._kf_frames = list(state["dropped"]), dict(state["keyframe_frames"])
        self.process_seconds, self.frames_done = state["process_seconds"], state["frames_done"]
        self._final = state["final"]
        self._buffer = list(state["pending"])
        # the child resumes after the frames of the buffered messages (already tracked)
        self.cursor = int(state["cursor"])
        for msg in self._buffer:
            if msg[0] == "frame":
                self.cursor = max(self.cursor, msg[1] + 1)


# ---------------------------------------------------------------------- child side
def _next_live(timestamps: np.ndarray, i: int, t0: float, ts0: float, rate: float) -> tuple[int, list[int]]:
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
            i, dropped = _next_live(timestamps, i, t0, ts0, rate)
        yield prepare(sequence[i]), dropped
        i += 1


class _FrameSource:
    """The child's frames, read (decoded, depth registered) and prepared (the frontend's
    `prepare`: feature extraction) ahead of the tracking of the previous frame: in a process of
    their own when the frontend has a picklable `preparer` (no interpreter lock shared with
    tracking), else in a background thread (OpenCV's decoders and ORB release the GIL).

    process: every frame in order, up to `ahead` read in advance. live: a camera; frame i is read
    at its time (rate x wall clock) into a one-frame slot; a frame still in the slot when the next
    arrives, or whose time passed before it could be read, is dropped (the tracker always gets
    the newest image, as from a live driver).
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

    def stop(self) -> None:
        with self._cv:
            self._stop = True
            self._cv.notify_all()


def _private_pipes():
    """The parent's command and message pipes (this process's stdin / stdout) moved to descriptors
    of their own, with stdin then /dev/null and stdout stderr: processes started from here (the
    frame reader, multiprocessing's resource tracker) inherit descriptors 0-2, and must neither
    keep the command pipe open (its end of stream would never come) nor write into the messages."""
    commands, messages = os.fdopen(os.dup(0), "rb"), os.fdopen(os.dup(1), "wb")
    devnull = os.open(os.devnull, os.O_RDONLY)
    os.dup2(devnull, 0)
    os.close(devnull)
    sys.stdout.flush()
    os.dup2(2, 1)
    return commands, messages


def _serve() -> None:
    """Child: ("start", make_frontend, sequence, mode, rate, cursor, state), then frames until the
    end or ("close",); answers ("state",) between frames; reports ("frame", ...), ("done", ...)."""
    stdin, stdout = _private_pipes()
    lock = threading.Lock()

    def send(msg) -> None:
        with lock:
            pickle.dump(msg, stdout, protocol=pickle.HIGHEST_PROTOCOL)
            stdout.flush()

    commands: queue.Queue = queue.Queue()
    try:
        _, make_frontend, sequence, mode, rate, cursor, state = pickle.load(stdin)

        def read_commands() -> None:
            while True:
                try:
                    commands.put(pickle.load(stdin)[0])
                except (EOFError, OSError, pickle.UnpicklingError):
                    commands.put("close")
                    return

        threading.Thread(target=read_commands, daemon=True).start()
        frontend = make_frontend()
        if state is not None:
            frontend.load_state_dict(state)
        _track(frontend, sequence, mode, rate, cursor, commands, send)
    except BaseException as exc:  # reported to the parent, which raises
        import traceback

        send(("error", f"{type(exc).__name__}: {exc}\n{traceback.format_exc(limit=8)}"))


def _track(frontend: Frontend, sequence: Sequence, mode: str, rate: float, cursor: int,
           commands: queue.Queue, send) -> None:
    t0 = time.perf_counter()
    source = _FrameSource(sequence, int(cursor), mode == "live", rate, prepare=frontend.prepare,
                          preparer=frontend.preparer())

    def serve_commands(block: bool) -> bool:
        """Answer pending commands; False when the parent asks the child to end."""
        while True:
            try:
                cmd = commands.get(block=block)
            except queue.Empty:
                return True
            if cmd == "close":
                return False
            if cmd == "state":
                send(("state", frontend.state_dict()))

    while True:
        if not serve_commands(block=False):
            source.stop()
            return
        frame, dropped = source.next()
        if frame is None:
            tail = dropped
            break
        ts = time.perf_counter()
        res = frontend.process(frame)
        # the frame's own cost: tracking plus the features the source built ahead (their wall
        # time, kept on the prepared frame), as when process() builds them
        seconds = time.perf_counter() - ts + prepared_seconds(frame)
        send(("frame", frame.index, res.w2c, frontend.poll(), frontend.keyframe_frames(), seconds, dropped))
    update = frontend.finish()
    report = {"trajectory": frontend.trajectory(), "lost": frontend.lost_frames(),
              "keyframe_frames": frontend.keyframe_frames(), "wall_s": time.perf_counter() - t0,
              "dropped": tail, "stats": frontend.stats() if hasattr(frontend, "stats") else {}}
    send(("done", update, report))
    while serve_commands(block=True):  # state requests until the parent closes
        pass


if __name__ == "__main__":
    process_settings.apply()
    _serve()
