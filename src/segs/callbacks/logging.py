"""Tensorboard image pairs (a render beside its ground truth every n steps) and the progress bar."""
from __future__ import annotations

import lightning as L
import torch
from lightning.pytorch.callbacks import TQDMProgressBar

from segs.callbacks.cadence import StepCadence
from segs.modules.contract import GaussianMapper


class ImageLogger(L.Callback):
    """Every `every_n_steps` logs [render | ground truth] of the first training view, skipping a
    due step that comes less than `min_interval_s` seconds after the previous image."""

    def __init__(self, every_n_steps: int = 500, min_interval_s: float = 0.0):
        self.cadence = StepCadence(every_n_steps, min_interval_s)  # the first due step logs

    def on_train_batch_end(self, trainer, pl_module: GaussianMapper, outputs, batch, batch_idx) -> None:
        step = trainer.global_step
        if trainer.logger is None or not self.cadence.due(step):
            return
        experiment = getattr(trainer.logger, "experiment", None)
        kf = pl_module.first_view()
        if kf is None or experiment is None or not hasattr(experiment, "add_image"):
            return
        self.cadence.done()
        render = pl_module.render_image(kf.w2c, kf.camera, kf.kf_id)["image"]
        pair = torch.cat([render, kf.rgb()], dim=1).clamp(0, 1)
        experiment.add_image("render_vs_gt", pair.permute(2, 0, 1), global_step=step)


class StepProgressBar(TQDMProgressBar):
    """Lightning's tqdm bar, showing the mapper's `progress_values` (loss, Gaussians) beside its
    own figures: the mapper sets them on the steps it writes to the loggers, without `self.log`."""

    def get_metrics(self, trainer, pl_module) -> dict:
        values = getattr(pl_module, "progress_values", {})
        shown = {k: int(v) if float(v).is_integer() else f"{v:.4g}" for k, v in values.items()}  # counts as integers
        return {**super().get_metrics(trainer, pl_module), **shown}
