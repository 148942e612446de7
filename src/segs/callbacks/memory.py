"""Memory bound: resident memory is logged and kept under a configured limit."""
from __future__ import annotations

from pathlib import Path

import lightning as L
import psutil

from segs.callbacks.checkpoint import save_atomic
from segs.errors import LimitError


def rss_mb() -> float:
    """Current resident set size of this process in MB."""
    return psutil.Process().memory_info().rss / 1e6


class MemoryGuard(L.Callback):
    """Every `every_n_steps` logs RSS (system/rss_mb) and its peak; above `max_rss_mb` it writes
    checkpoints/last.ckpt and stops the run with a LimitError (exit 2) instead of being killed.
    """

    def __init__(self, max_rss_mb: float | None = None, every_n_steps: int = 10, dirpath: str | None = None):
        if max_rss_mb is not None and max_rss_mb <= 0:
            raise LimitError(f"limits.max_rss_mb={max_rss_mb} is out of range: expected > 0 or null")
        self.max_rss_mb, self.every_n_steps, self.dirpath = max_rss_mb, every_n_steps, dirpath
        self.peak_mb = 0.0

    def check(self, trainer, where: str) -> None:
        now = rss_mb()
        self.peak_mb = max(self.peak_mb, now)
        if self.max_rss_mb is not None and now > self.max_rss_mb:
            ckpt = save_atomic(trainer, Path(self.dirpath or trainer.default_root_dir) / "checkpoints" / "last.ckpt")
            raise LimitError(
                f"memory limit limits.max_rss_mb={self.max_rss_mb:g} exceeded ({now:.0f} MB {where}); "
                f"checkpoint {ckpt}; lower model.max_anchors / model.budget_mb / data.downscale or raise the limit"
            )

    def on_train_start(self, trainer, pl_module) -> None:
        self.check(trainer, "after the initial keyframes")

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        if self.every_n_steps and trainer.global_step % self.every_n_steps == 0:
            self.check(trainer, f"at step {trainer.global_step}")
            pl_module.log("system/rss_mb", rss_mb(), on_step=True, on_epoch=False)
