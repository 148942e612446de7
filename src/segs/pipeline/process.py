"""Frame sources whose frontend runs in a child process: SLAM beside mapping, on another core.

gtsam and the ORB frontend's Python keep the GIL, so a tracking thread beside training slows
both; in a child process the frontend uses its own core and the mapper receives its MapUpdates
through a queue, as ORB-SLAM's tracking / local-mapping threads hand keyframes to a renderer.

`ProcessSource` is a frame source (segs.pipeline.sources) whose frames are read and tracked by the
child, which owns the sequence and runs the frame loop (segs.pipeline.loop) on them; the parent
starts the child, takes its reports (`track`) and answers for the trajectory / keyframes / lost
frames from them. Two pacings:

- `ProcessSource` ("process"): every frame, as fast as the frontend tracks (deterministic in what
  it computes, only the moment updates arrive varies);
- `LiveSource` ("live"): frames at their timestamps (wall clock from the first one, x `rate`), like a camera.
  When tracking falls behind, the frames whose time has passed are dropped and the newest one is
  tracked (a live camera driver delivers the latest image); they are counted in dropped_frames(),
  never invented poses.

The child is `python -m segs.pipeline.process` (pickles on stdin / stdout, like ba_process), so it
imports only the frontend's modules (no torch, no Lightning). Checkpoints: state_dict() asks the
child for its frontend state at a frame boundary and keeps every update the mapper has not
taken yet beside it, so a resumed run loses and repeats nothing.
"""
from __future__ import annotations

import os
import pickle
import queue
import subprocess
import sys
import threading
import time
from typing import Any, Callable

import numpy as np

from segs import process_settings
from segs.data.frame import Sequence
from segs.errors import ConfigError
from segs.pipeline.loop import FrameLoop
from segs.pipeline.readers import CameraFrames
from segs.pipeline.sources import FrameSource
from segs.slam.base import STATE_FORMAT, Frontend, MapUpdate


class ProcessSource(FrameSource):
    """A frontend (built by make_frontend() in the child) tracking every frame of `sequence` in a
    child process, at its own pace.

    make_frontend: picklable callable -> Frontend (e.g. the slam config's partial with camera and
    sensor bound); uses_ground_truth_poses: what the frontend built by make_frontend says of
    itself. The child starts with the first track() (or start()); finish() waits for the end of
    the sequence.
    """

    mode, paced = "process", False

    def __init__(self, make_frontend: Callable[[], Frontend], sequence: Sequence, uses_ground_truth_poses: bool = False,
                 rate: float = 1.0):  # fmt: skip
        super().__init__(sequence)
        if not rate > 0:
            raise ConfigError(f"slam_rate={rate!r} must be > 0")
        self.make_frontend, self.rate = make_frontend, float(rate)
        self.uses_ground_truth_poses = bool(uses_ground_truth_poses)
        self._proc: subprocess.Popen | None = None
        self._inbox: queue.Queue = queue.Queue()  # messages read from the child, in order
        self._buffer: list[tuple] = []  # messages taken from the inbox, not yet returned by track()
        self._resume: dict | None = None
        self._reset()

    def _reset(self) -> None:
        self._cursor = 0  # next frame the child will read
        self._traj: dict[int, np.ndarray] = {}  # frame -> w2c as tracked (final poses after finish)
        self._lost: set[int] = set()
        self._dropped: list[int] = []
        self._kf_frames: dict[int, int] = {}
        self._final: dict | None = None  # the child's closing report
        self._process_seconds = 0.0  # seconds the child spent in frontend.process
        self._frames_done = 0
        self.wall_seconds = 0.0  # the child's time from its first frame to the end of finish()

    # ------------------------------------------------------------------ child control
    def start(self) -> None:
        """Start the child (once); it begins at self.cursor with the restored state, if any."""
        if self._proc is not None or self._final is not None:  # running, or the sequence is done
            return
        self._proc = subprocess.Popen([sys.executable, "-m", "segs.pipeline.process"], stdin=subprocess.PIPE,
                                      stdout=subprocess.PIPE)
        state = self._resume.get("frontend") if self._resume else None
        self._send(("start", self.make_frontend, self.sequence, self.mode, self.rate, self._cursor, state))
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
            self._process_seconds += seconds
            self._frames_done += 1
            self._cursor = index + 1
            return update
        if msg[0] == "done":
            _, update, report = msg
            self._final = report
            self._traj, self._lost = report["trajectory"], set(report["lost"])
            self._kf_frames, self.wall_seconds = report["keyframe_frames"], report["wall_s"]
            self._dropped.extend(report["dropped"])
            self._cursor = len(self.sequence)
            return update
        raise RuntimeError(f"unexpected message from the slam frontend process: {msg[0]!r}")

    # ------------------------------------------------------------------ FrameSource API
    @property
    def cursor(self) -> int:
        return self._cursor

    @property
    def frames_done(self) -> int:
        """Frames the child tracked (live: fewer than the sequence's when frames were dropped)."""
        return self._frames_done

    @property
    def process_seconds(self) -> float:
        """The child's own time in frontend.process."""
        return self._process_seconds

    def track(self, frames: int = 1, timeout: float = 0.0) -> MapUpdate:
        """Everything the child reported since the previous call (`frames` does not apply: the
        child tracks at its own pace); with a timeout > 0 and nothing reported yet, waits up to
        that many seconds for the first message."""
        self.start()
        up = MapUpdate()
        for msg in self._buffer:
            up = up.merge(self._apply(msg))
        if timeout > 0 and not self._buffer and not self.exhausted():
            msg = self._next(block=True, timeout=timeout)
            if msg is not None:
                up = up.merge(self._apply(msg))
        self._buffer = []
        while (msg := self._next(block=False)) is not None:
            up = up.merge(self._apply(msg))
        return up

    def exhausted(self) -> bool:
        """The child has tracked every frame and finished (its final update is taken)."""
        return self._final is not None

    def finish(self) -> MapUpdate:
        """Wait for the end of the sequence and the frontend's finish(); everything not taken."""
        up = self.track()
        while not self.exhausted():
            up = up.merge(self.track(timeout=0.1))
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
        out.update(mode=self.mode, frames_dropped=len(self._dropped), child_process_s=self._process_seconds,
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
        """The child's frontend state at a frame boundary, every report not taken yet and what
        the child reported so far, as arrays (format segs.state.v3)."""
        self.start()
        if self._proc is None:  # a resumed run whose sequence was already done
            inner = self._resume.get("frontend") if self._resume else None
        else:
            self._send(("state",))
            while (msg := self._next(block=True)) is not None and msg[0] != "state":
                self._buffer.append(msg)  # reported before the state: the mapper gets them later
            inner = msg[1] if msg is not None else None
        return {"format": STATE_FORMAT, "mode": self.mode, "frontend": inner, "pending": [_message_state(m) for m in self._buffer],
                "cursor": self._cursor, "trajectory": _poses_state(self._traj), "lost": np.array(sorted(self._lost), np.int64),
                "dropped": np.array(self._dropped, np.int64), "keyframe_frames": _ints_state(self._kf_frames),
                "process_seconds": self._process_seconds, "frames_done": self._frames_done,
                "final": None if self._final is None else _report_state(self._final)}  # fmt: skip

    def load_state_dict(self, state: dict) -> None:
        if state.get("format") == "segs.process.v1":  # before segs.state.v3: pickled updates, no mode
            state = _from_process_v1(state, self.mode)
        if state.get("format") != STATE_FORMAT or "pending" not in state:
            raise ConfigError(f"slam: the checkpoint's frame source state is {state.get('format')!r}, not a frontend-process "
                              "state; resume with the same slam_mode")  # fmt: skip
        if state["mode"] != self.mode:
            raise ConfigError(f"slam: the checkpoint's frontend ran with slam_mode={state['mode']}, this run with "
                              f"slam_mode={self.mode}; resume with the same slam_mode")  # fmt: skip
        if self._proc is not None:
            raise RuntimeError("load_state_dict before the frontend process starts")
        self._reset()
        self._resume = state
        self._traj, self._lost = _poses_from(state["trajectory"]), set(state["lost"].tolist())
        self._dropped, self._kf_frames = state["dropped"].tolist(), _ints_from(state["keyframe_frames"])
        self._process_seconds, self._frames_done = float(state["process_seconds"]), int(state["frames_done"])
        self._final = None if state["final"] is None else _report_from(state["final"])
        self._buffer = [_message_from(m) for m in state["pending"]]
        # the child resumes after the frames of the buffered messages (already tracked)
        self._cursor = int(state["cursor"])
        for msg in self._buffer:
            if msg[0] == "frame":
                self._cursor = max(self._cursor, msg[1] + 1)


# ---------------------------------------------------------------------- the state's arrays
def _poses_state(poses: dict[int, np.ndarray]) -> dict:
    return {"frame": np.array(list(poses), np.int64), "w2c": np.array(list(poses.values()), np.float64).reshape(-1, 4, 4)}


def _poses_from(state: dict) -> dict[int, np.ndarray]:
    return {k: w.copy() for k, w in zip(state["frame"].tolist(), state["w2c"])}


def _ints_state(d: dict[int, int]) -> dict:
    return {"key": np.array(list(d), np.int64), "value": np.array(list(d.values()), np.int64)}


def _ints_from(state: dict) -> dict[int, int]:
    return dict(zip(state["key"].tolist(), state["value"].tolist()))


def _report_state(r: dict) -> dict:
    """The child's closing report (trajectory, lost, keyframes, wall time, dropped, stats)."""
    return {"trajectory": _poses_state(r["trajectory"]), "lost": np.array(r["lost"], np.int64),
            "keyframe_frames": _ints_state(r["keyframe_frames"]), "wall_s": float(r["wall_s"]),
            "dropped": np.array(r["dropped"], np.int64), "stats": dict(r["stats"])}  # fmt: skip


def _report_from(state: dict) -> dict:
    return {"trajectory": _poses_from(state["trajectory"]), "lost": state["lost"].tolist(),
            "keyframe_frames": _ints_from(state["keyframe_frames"]), "wall_s": state["wall_s"],
            "dropped": state["dropped"].tolist(), "stats": dict(state["stats"])}  # fmt: skip


def _message_state(msg: tuple) -> dict:
    """A ("frame", ...) or ("done", ...) message of the child as arrays."""
    if msg[0] == "frame":
        _, index, w2c, update, kf_frames, seconds, dropped = msg
        return {"kind": "frame", "index": int(index), "w2c": w2c, "update": update.state_dict(),
                "keyframe_frames": _ints_state(kf_frames), "seconds": float(seconds), "dropped": np.array(dropped, np.int64)}  # fmt: skip
    _, update, report = msg
    return {"kind": "done", "update": update.state_dict(), "report": _report_state(report)}


def _message_from(state: dict) -> tuple:
    if state["kind"] == "frame":
        return ("frame", state["index"], state["w2c"], MapUpdate.from_state(state["update"]), _ints_from(state["keyframe_frames"]),
                state["seconds"], state["dropped"].tolist())  # fmt: skip
    return ("done", MapUpdate.from_state(state["update"]), _report_from(state["report"]))


def _from_process_v1(state: dict, mode: str) -> dict:
    """A "segs.process.v1" state (pickled messages and MapUpdates; no slam_mode: this run's is
    assumed) in the v3 layout; its frontend state is converted by the frontend in the child."""
    return {"format": STATE_FORMAT, "mode": mode, "frontend": state["frontend"], "pending": [_message_state(m) for m in state["pending"]],
            "cursor": state["cursor"], "trajectory": _poses_state(state["trajectory"]), "lost": np.array(state["lost"], np.int64),
            "dropped": np.array(state["dropped"], np.int64), "keyframe_frames": _ints_state(state["keyframe_frames"]),
            "process_seconds": state["process_seconds"], "frames_done": state["frames_done"],
            "final": None if state["final"] is None else _report_state(state["final"])}  # fmt: skip


class LiveSource(ProcessSource):
    """A ProcessSource whose child reads the frames like a camera: at their timestamps x `rate`
    (1 = real time), the newest when tracking is behind (the others dropped, see the module
    docstring)."""

    mode = "live"


# ---------------------------------------------------------------------- child side
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
    """The frame loop over the camera's frames, one ("frame", ...) message per frame, then the
    frontend's finish and ("done", update, report)."""
    t0 = time.perf_counter()
    camera = CameraFrames(sequence, int(cursor), mode == "live", rate, prepare=frontend.prepare,
                          preparer=frontend.preparer())
    loop = FrameLoop(frontend, iter(camera))

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
            camera.stop()
            return
        tracked = loop.step()
        if tracked is None:
            break
        send(("frame", tracked.frame.index, tracked.result.w2c, loop.poll(), frontend.keyframe_frames(), tracked.seconds,
              tracked.dropped))  # fmt: skip
    update = loop.finish()
    report = {"trajectory": frontend.trajectory(), "lost": frontend.lost_frames(),
              "keyframe_frames": frontend.keyframe_frames(), "wall_s": time.perf_counter() - t0,
              "dropped": camera.tail_dropped, "stats": frontend.stats() if hasattr(frontend, "stats") else {}}
    send(("done", update, report))
    while serve_commands(block=True):  # state requests until the parent closes
        pass


if __name__ == "__main__":
    process_settings.apply()
    _serve()
