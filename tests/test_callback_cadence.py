"""Periodic checkpoints and tensorboard images: every n steps, at most one per min_interval_s."""
from types import SimpleNamespace

import torch

from segs.callbacks import cadence
from segs.callbacks import checkpoint as ckpt_mod
from segs.callbacks.checkpoint import PeriodicCheckpoint
from segs.callbacks.logging import ImageLogger


class Clock:
    def __init__(self):
        self.t = 1000.0

    def __call__(self):
        return self.t


def _steps(callback, trainer, clock, seconds_per_step, n):
    """Runs the callback's batch-end hook for steps 1..n, the clock advancing per step."""
    for step in range(1, n + 1):
        clock.t += seconds_per_step
        trainer.global_step = step
        callback.on_train_batch_end(trainer, trainer.module, None, None, step - 1)


def test_periodic_checkpoint_skips_due_steps_inside_the_interval(monkeypatch, tmp_path):
    clock, saved = Clock(), []
    monkeypatch.setattr(cadence.time, "monotonic", clock)
    monkeypatch.setattr(ckpt_mod, "save_atomic", lambda trainer, path: saved.append(trainer.global_step))
    trainer = SimpleNamespace(global_step=0, default_root_dir=str(tmp_path), module=None)
    slow = PeriodicCheckpoint(every_n_steps=10, dirpath=str(tmp_path), min_interval_s=5.0)
    slow.on_train_start(trainer, None)
    _steps(slow, trainer, clock, 1.0, 40)  # 10 s per 10 steps: every due step is written
    assert saved == [10, 20, 30, 40]
    saved.clear()
    fast = PeriodicCheckpoint(every_n_steps=10, dirpath=str(tmp_path), min_interval_s=5.0)
    fast.on_train_start(trainer, None)
    _steps(fast, trainer, clock, 0.2, 100)  # 2 s per 10 steps: one write per 5 s at most
    assert saved == [30, 60, 90]
    saved.clear()
    plain = PeriodicCheckpoint(every_n_steps=10, dirpath=str(tmp_path))  # min_interval_s 0: every due step
    _steps(plain, trainer, clock, 0.0, 30)
    assert saved == [10, 20, 30]


def test_image_logger_logs_the_first_due_step_then_at_most_one_per_interval(monkeypatch):
    clock, logged = Clock(), []
    monkeypatch.setattr(cadence.time, "monotonic", clock)
    kf = SimpleNamespace(w2c=torch.eye(4), camera=None, kf_id=0, rgb=lambda: torch.zeros(2, 3, 3))
    module = SimpleNamespace(first_view=lambda: kf, render_image=lambda w2c, cam, kf_id: {"image": torch.ones(2, 3, 3)})
    experiment = SimpleNamespace(add_image=lambda tag, img, global_step: logged.append(global_step))
    trainer = SimpleNamespace(global_step=0, logger=SimpleNamespace(experiment=experiment), module=module)
    _steps(ImageLogger(every_n_steps=5, min_interval_s=3.0), trainer, clock, 0.2, 50)  # 1 s per 5 steps
    assert logged == [5, 20, 35, 50]
