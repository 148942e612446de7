"""Ctrl-C / SIGTERM stop training at the next step boundary, after writing a resumable checkpoint.

The first signal sets a flag; the step in progress finishes, then the callback writes
checkpoints/last.ckpt (atomically: model, optimizer, keyframes, SLAM map and trajectory, step,
RNG states) and trajectory_partial.txt, prints how to resume and stops the trainer; segs.train
then exits with 130 (SIGINT) or 143 (SIGTERM). A second signal restores the default behaviour.
"""
from __future__ import annotations

import logging
import signal
import sys
from pathlib import Path

import lightning as L

from segs.callbacks.checkpoint import save_atomic

log = logging.getLogger(__name__)

EXIT_CODES = {signal.SIGINT: 130, signal.SIGTERM: 143}


class GracefulInterrupt(L.Callback):
    """Installs SIGINT / SIGTERM handlers for the duration of fit."""

    def __init__(self, dirpath: str | None = None):
        self.dirpath = dirpath
        self.received: int | None = None
        self._previous: dict[int, object] = {}
        self.checkpoint: Path | None = None

    def _handler(self, signum, frame) -> None:
        if self.received is not None:  # second signal: give the user the default behaviour back
            self._restore()
            signal.raise_signal(signum)
            return
        self.received = signum
        print(f"\nsegs: {signal.Signals(signum).name} received, stopping after this step (again to abort)", file=sys.stderr)

    def _restore(self) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous = {}

    def on_fit_start(self, trainer, pl_module) -> None:
        try:
            for sig in EXIT_CODES:
                self._previous[sig] = signal.signal(sig, self._handler)
        except ValueError:  # not the main thread (e.g. some launchers): signals stay as they are
            self._previous = {}

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        if self.received is None or trainer.should_stop:
            return
        self.stop(trainer)

    def stop(self, trainer) -> None:
        """Checkpoint, partial trajectory, resume hint; then ask the trainer to stop."""
        out = Path(self.dirpath or trainer.default_root_dir)
        self.checkpoint = save_atomic(trainer, out / "checkpoints" / "last.ckpt")
        bridge = next((c for c in trainer.callbacks if hasattr(c, "write_partial_trajectory")), None)
        if bridge is not None:
            bridge.write_partial_trajectory(out / "trajectory_partial.txt")
        print(
            f"segs: interrupted at step {trainer.global_step}; checkpoint {self.checkpoint}\n"
            f"segs: resume with the same command plus  ckpt_path={self.checkpoint}",
            file=sys.stderr,
        )
        trainer.should_stop = True

    def on_fit_end(self, trainer, pl_module) -> None:
        self._restore()

    def on_exception(self, trainer, pl_module, exception) -> None:
        self._restore()

    @property
    def exit_code(self) -> int | None:
        return EXIT_CODES.get(self.received) if self.received is not None else None
