"""Ctrl-C / SIGTERM: stop cleanly, keep the work done so far, never a traceback.

This is the one place that handles them: segs.train makes it the first callback of every trainer
and installs the handlers for the whole run (`with interrupt:`; used as a plain Lightning callback
they are installed for the duration of fit). Lightning registers a SIGTERM handler of its own when
fit starts (it would stop the loop with SIGTERMException, exit status 0); `on_train_start` takes
both signals back, before the bridge tracks the first frames. What a first signal does depends
on the phase the run is in:

- "step" (training): the step in progress finishes, then checkpoints/last.ckpt (atomically:
  model, optimizer, keyframes, SLAM map and trajectory, step, RNG states),
  trajectory_partial.txt and map_points.ply are written, the resume command is printed and the trainer stops;
  segs.train exits with 130 (SIGINT) or 143 (SIGTERM).
- "defer" (writing the final checkpoint): the write finishes, then the run stops the same way.
- "now" (tracking the rest, evaluating): :class:`Interrupted` is raised at once; segs.train
  prints one line and exits 130 / 143 without writing metrics.json.

A second signal always raises :class:`Interrupted` at once (an atomic checkpoint write in progress
removes its temporary file, the previous checkpoint stays intact).
"""
from __future__ import annotations

import contextlib
import logging
import signal
import sys
from pathlib import Path
from typing import Iterator

import lightning as L

from segs.callbacks.bridge import SlamBridge
from segs.callbacks.checkpoint import save_atomic
from segs.map_points import FILE_NAME as MAP_POINTS

log = logging.getLogger(__name__)

EXIT_CODES = {signal.SIGINT: 130, signal.SIGTERM: 143}
PHASES = ("step", "defer", "now")


class Interrupted(BaseException):
    """A signal stopped the run where no step boundary could be waited for.

    BaseException like KeyboardInterrupt (so `except Exception` does not swallow it), but not a
    KeyboardInterrupt: Lightning turns that one into exit status 1."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum
        self.code = EXIT_CODES.get(signum, 1)


class GracefulInterrupt(L.Callback):
    """SIGINT / SIGTERM handlers with a phase-dependent first signal (see the module doc)."""

    def __init__(self, dirpath: str | None = None):
        self.dirpath = dirpath
        self.received: int | None = None
        self.phase = "step"
        self.checkpoint: Path | None = None
        self._previous: dict[int, object] = {}
        self._owner: str | None = None  # "run" (context manager) or "fit" (Lightning hooks)

    def _handler(self, signum, frame) -> None:
        first = self.received is None
        if first:
            self.received = signum
        if not first or self.phase == "now":
            raise Interrupted(signum)
        when = "this step" if self.phase == "step" else "the checkpoint is written"
        print(f"\nsegs: {signal.Signals(signum).name} received, stopping after {when} (again to abort)", file=sys.stderr)

    # -- installing the handlers -----------------------------------------------------------------
    def install(self, owner: str) -> None:
        if self._owner is not None:
            return
        try:
            for sig in EXIT_CODES:
                self._previous[sig] = signal.signal(sig, self._handler)
            self._owner = owner
        except ValueError:  # not the main thread (e.g. some launchers): signals stay as they are
            self._restore()

    def _restore(self) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous, self._owner = {}, None

    def __enter__(self) -> "GracefulInterrupt":
        self.install("run")
        return self

    def __exit__(self, *exc) -> None:
        if self._owner == "run":
            self._restore()

    @contextlib.contextmanager
    def in_phase(self, phase: str) -> Iterator[None]:
        """Handle a first signal as `phase` ("step", "defer" or "now") inside the block."""
        if phase not in PHASES:
            raise ValueError(f"phase must be one of {PHASES}, got {phase!r}")
        before, self.phase = self.phase, phase
        try:
            if phase == "now" and self.received is not None:
                raise Interrupted(self.received)
            yield
        finally:
            self.phase = before

    # -- Lightning hooks -------------------------------------------------------------------------
    def on_fit_start(self, trainer, pl_module) -> None:
        self.install("fit")

    def on_train_start(self, trainer, pl_module) -> None:
        """Lightning has put its SIGTERM handler in front of this one (after on_fit_start, and
        restores this one when fit ends): take both signals back for the training loop."""
        if self._owner is not None:
            for sig in EXIT_CODES:
                signal.signal(sig, self._handler)

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        if self.received is None or trainer.should_stop:
            return
        self.stop(trainer)

    def stop(self, trainer) -> None:
        """Checkpoint, partial trajectory, resume hint; then ask the trainer to stop."""
        out = Path(self.dirpath or trainer.default_root_dir)
        self.checkpoint = save_atomic(trainer, out / "checkpoints" / "last.ckpt")
        bridge = next((c for c in trainer.callbacks if isinstance(c, SlamBridge)), None)
        if bridge is not None:
            bridge.run.write_partial_trajectory(out / "trajectory_partial.txt")
            bridge.run.map_points.write(out / MAP_POINTS)
        print(
            f"segs: interrupted at step {trainer.global_step}; checkpoint {self.checkpoint}\n"
            f"segs: resume with the same command plus  ckpt_path={self.checkpoint}",
            file=sys.stderr,
        )
        trainer.should_stop = True

    def on_fit_end(self, trainer, pl_module) -> None:
        if self._owner == "fit":
            self._restore()

    def on_exception(self, trainer, pl_module, exception) -> None:
        if self._owner == "fit":
            self._restore()

    @property
    def exit_code(self) -> int | None:
        return EXIT_CODES.get(self.received) if self.received is not None else None
