"""Memory bound: resident memory is logged and kept under a configured limit.

Every figure is in MB = 10^6 bytes (limits.max_rss_mb, system/rss_mb, metrics.json peak_rss_mb).
The guard watches the whole run: tracking until mapping starts and the tracking of the frames
left after training (the SLAM bridge calls :meth:`MemoryGuard.check`), every n training steps, and
every test view of the evaluation (segs.train passes :meth:`MemoryGuard.check` to evaluate).
"""
from __future__ import annotations

import resource
from pathlib import Path

import lightning as L
import psutil
import torch

from segs.callbacks.checkpoint import save_atomic
from segs.errors import LimitError

MB = 1e6


def rss_mb() -> float:
    """Current resident set size of this process in MB."""
    return psutil.Process().memory_info().rss / MB


def peak_rss_mb() -> float:
    """Peak resident set size of this process in MB (Linux reports KiB). The kernel's high-water
    mark is synced from per-thread counters lazily and can trail the current RSS by a few hundred
    KB, so the current RSS is taken when larger."""
    return max(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / MB, rss_mb())


class MemoryGuard(L.Callback):
    """Every `every_n_steps` steps (and frames / test views outside training) checks RSS and logs
    it (system/rss_mb); above `max_rss_mb` it stops the run with a LimitError (exit 2) instead of
    being killed, after writing checkpoints/last.ckpt when training state is at stake.
    """

    def __init__(self, max_rss_mb: float | None = None, every_n_steps: int = 10, dirpath: str | None = None):
        if max_rss_mb is not None and max_rss_mb <= 0:
            raise LimitError(f"limits.max_rss_mb={max_rss_mb} is out of range: expected > 0 or null")
        self.max_rss_mb, self.every_n_steps, self.dirpath = max_rss_mb, every_n_steps, dirpath
        self.peak_mb = 0.0

    def check(self, trainer, where: str, save: bool = True) -> None:
        """LimitError when RSS is above the limit; save: write checkpoints/last.ckpt first."""
        now = rss_mb()
        self.peak_mb = max(self.peak_mb, now)
        if self.max_rss_mb is None or now <= self.max_rss_mb:
            return
        ckpt = "no new checkpoint"
        if save and trainer is not None:
            ckpt = f"checkpoint {save_atomic(trainer, Path(self.dirpath or trainer.default_root_dir) / 'checkpoints' / 'last.ckpt')}"
        raise LimitError(
            f"memory limit limits.max_rss_mb={self.max_rss_mb:g} exceeded ({now:.0f} MB {where}); "
            f"{ckpt}; lower model.max_anchors / model.budget_mb / data.downscale or raise the limit"
        )

    def on_train_start(self, trainer, pl_module) -> None:
        self.check(trainer, "after the initial keyframes")

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        if self.every_n_steps and trainer.global_step % self.every_n_steps == 0:
            self.check(trainer, f"at step {trainer.global_step}")
            pl_module.log("system/rss_mb", torch.tensor(rss_mb()), on_step=True, on_epoch=False)  # a host tensor: no copy to a GPU
