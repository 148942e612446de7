"""Periodic checkpoints written atomically (temporary file + rename)."""
from __future__ import annotations

import contextlib
import os
from pathlib import Path

import lightning as L
import torch
from lightning.pytorch.plugins.io import TorchCheckpointIO

from segs.callbacks.cadence import StepCadence


class DirectCheckpointIO(TorchCheckpointIO):
    """Lightning's TorchCheckpointIO writing straight to the file with torch.save.

    Lightning's serialises the whole checkpoint into an in-memory buffer and copies it out before
    writing (twice its size in resident memory: 25 MB each for the sample's); `save_atomic`
    already writes a temporary file and renames it, which is what that buffer was for."""

    def save_checkpoint(self, checkpoint: dict, path, storage_options=None) -> None:
        if storage_options is not None:
            raise TypeError("DirectCheckpointIO takes no storage_options")
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        torch.save(checkpoint, str(path))


def save_atomic(trainer: L.Trainer, path: str | Path) -> Path:
    """trainer.save_checkpoint to path via a temporary file, so a kill leaves the old file intact.

    A write that fails or is interrupted (disk full, read-only folder, a second Ctrl-C) removes
    its temporary file and re-raises; only kill -9 can leave `<path>.tmp` behind.
    """
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        trainer.save_checkpoint(str(tmp))
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        raise
    return path


class PeriodicCheckpoint(L.Callback):
    """Writes <dirpath>/last.ckpt every `every_n_steps` steps (0 = never periodically), skipping a
    due step that comes less than `min_interval_s` seconds after the previous write (or the start
    of training): a fast device's steps do not turn checkpoints into a share of the run."""

    def __init__(self, every_n_steps: int = 1000, dirpath: str | None = None, min_interval_s: float = 0.0):
        self.cadence = StepCadence(every_n_steps, min_interval_s)
        self.cadence.restart()
        self.dirpath = dirpath

    def on_train_start(self, trainer, pl_module) -> None:
        self.cadence.restart()

    def path(self, trainer: L.Trainer) -> Path:
        return Path(self.dirpath or Path(trainer.default_root_dir) / "checkpoints") / "last.ckpt"

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        if trainer.global_step > 0 and self.cadence.due(trainer.global_step):
            save_atomic(trainer, self.path(trainer))
            self.cadence.done()
