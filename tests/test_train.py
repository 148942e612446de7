"""End-to-end CPU training on a tiny synthetic sequence: outputs, loss, resume."""
from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from plyfile import PlyData

from segs.train import run

OUTPUTS = ["metrics.json", "trajectory.txt", "point_cloud.ply", "test_views.csv", "checkpoints/final.ckpt"]


def test_short_training_lowers_loss_and_writes_every_output(tiny_cfg, tmp_path):
    cfg = tiny_cfg("trainer.max_steps=60", "callbacks.periodic_checkpoint.every_n_steps=0")
    metrics = run(cfg)
    out = Path(cfg.paths.output_dir)
    for name in OUTPUTS:
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    assert len(list((out / "renders").glob("*.png"))) == 2
    m = json.loads((out / "metrics.json").read_text())
    assert m["status"] == "finished" and m["iterations"] == 60
    assert m["test_views"] > 0 and 5 < m["psnr"] < 60 and 0 < m["ssim"] <= 1
    assert m["lpips"] is None and "n/a" in m["lpips_note"]
    assert m["ate_rmse_m"] is None and m["ate"]["reason"] == "ground-truth poses"  # known poses: nothing to score
    assert m["anchors"] > 0 and m["gaussians"] == 10 * m["anchors"]
    ply = PlyData.read(str(out / "point_cloud.ply"))
    names = {p.name for p in ply["vertex"].properties}
    assert {"x", "y", "z", "f_dc_0", "opacity", "scale_0", "rot_0"} <= names
    assert metrics["psnr"] == m["psnr"]


def test_a_wall_clock_limit_stops_before_the_schedule_and_still_evaluates(tiny_cfg, capsys):
    cfg = tiny_cfg("trainer.max_steps=100000", "trainer.max_time=00:00:00:02", "callbacks.periodic_checkpoint.every_n_steps=0")
    m = run(cfg)
    assert m["status"] == "finished" and m["test_views"] > 0 and m["psnr"] is not None
    assert m["scheduled_iterations"] == 100000 and 0 < m["iterations"] < 100000
    assert f"{m['iterations']} of 100000 scheduled iterations" in capsys.readouterr().out


def test_loss_decreases(tiny_cfg):
    
    from segs.train import build, step_batches

    cfg = tiny_cfg("trainer.max_steps=80", "callbacks.periodic_checkpoint.every_n_steps=0", "eval.enabled=false")
    torch.manual_seed(0)
    t = build(cfg)
    module, trainer = t.module, t.trainer
    trainer.fit(module, step_batches(80))
    h = module.loss_history
    assert len(h) == 80
    assert sum(h[-10:]) / 10 < 0.85 * sum(h[:10]) / 10


def test_resume_continues_at_the_same_step_with_the_same_anchors(tiny_cfg, tmp_path):
    
    from segs.train import build, step_batches

    first = tiny_cfg("trainer.max_steps=30", "callbacks.periodic_checkpoint.every_n_steps=20",
                      "callbacks.periodic_checkpoint.min_interval_s=0", "eval.enabled=false", out=tmp_path / "a")
    t = build(first)
    module, trainer = t.module, t.trainer
    trainer.fit(module, step_batches(30))
    ckpt = tmp_path / "a" / "checkpoints" / "last.ckpt"
    assert ckpt.is_file()
    state = torch.load(ckpt, weights_only=False)
    assert state["global_step"] == 20
    n_anchors = state["state_dict"]["model.field.rows.xyz"].shape[0]

    second = tiny_cfg("trainer.max_steps=30", f"ckpt_path={ckpt}", "eval.enabled=false", out=tmp_path / "b")
    t = build(second)
    resumed, bridge, trainer2 = t.module, t.bridge, t.trainer
    seen = {}

    def on_start(trainer, pl_module):
        seen["step"] = trainer.global_step
        seen["anchors"] = len(pl_module.model.field)
        seen["views"] = pl_module.counts().training_views

    import lightning as L

    class Probe(L.Callback):
        def on_train_start(self, trainer, pl_module):
            on_start(trainer, pl_module)

    trainer2.callbacks.append(Probe())
    trainer2.fit(resumed, step_batches(30), ckpt_path=str(ckpt), weights_only=False)
    assert seen["step"] == 20 and seen["anchors"] == n_anchors and seen["views"] > 0
    assert trainer2.global_step == 30
    assert bridge.source.cursor == state["callbacks"]["SlamBridge"]["run"]["source"]["cursor"] or bridge.run.finished


@pytest.mark.slow
def test_afme_beats_no_afme_on_test_views_under_an_exposure_change(tiny_cfg, tmp_path):
    """The paper's AfME claim on a sequence built to isolate it: the camera turns in place (every
    surface point keeps one viewing ray, so view-dependent colour cannot explain the frame's
    exposure) while gain and white balance change smoothly over +-1 stop. AfME sees the test
    frame's pose only. Measured (seeds 0 / 1): 600 steps 25.8 / 22.1 dB against 20.6 / 20.5 dB;
    1000 steps 25.6 / 24.6 dB against 20.4 / 21.8 dB."""
    psnr = {}
    for kind in ("linear", "none"):
        cfg = tiny_cfg("trainer.max_steps=600", "data.n_frames=24", "data.exposure_change=1.0", "data.texture=poor",
                       "data.trajectory=pan", "slam.keyframe_every=1", "slam.point_source=grid", "eval.save_renders=0",
                       f"model.appearance.kind={kind}", "callbacks.periodic_checkpoint.every_n_steps=0", "eval.progress=false",
                       out=tmp_path / kind)  # fmt: skip
        psnr[kind] = run(cfg)["psnr"]
    assert psnr["linear"] > psnr["none"] + 1.0, psnr


def test_the_logger_gets_the_step_scalars_every_log_every_n_steps(tiny_cfg, tmp_path):
    """The mapper logs on the steps the logger writes (not every step): each write carries the
    loss, train/psnr and the anchors, at steps log_every_n_steps - 1, 2 * n - 1, ..."""
    from lightning.pytorch.loggers import Logger

    from segs.train import build, step_batches

    class Recorder(Logger):
        name, version = "recorder", 0

        def __init__(self):
            super().__init__()
            self.rows: list[tuple[int, dict]] = []

        def log_metrics(self, metrics, step=None):
            self.rows.append((step, dict(metrics)))

        def log_hyperparams(self, params, *args, **kwargs):
            pass

    def logged_steps(every: int) -> list[tuple[int, dict]]:
        cfg = tiny_cfg("trainer.max_steps=40", f"trainer.log_every_n_steps={every}",
                       "callbacks.periodic_checkpoint.every_n_steps=0", "eval.enabled=false", out=tmp_path / str(every))  # fmt: skip
        t = build(cfg)
        rec = Recorder()
        t.trainer.loggers = [rec]
        t.trainer.fit(t.module, step_batches(40))
        return [(s, m) for s, m in rec.rows if "loss" in m]

    rows = logged_steps(10)
    assert [s for s, _ in rows] == [9, 19, 29, 39]
    assert all({"train/psnr", "model/anchors", "train/iteration_ms"} <= set(m) for _, m in rows)
    assert logged_steps(0) == []  # 0: Lightning writes nothing, and the step does not divide by it


def test_a_non_finite_map_stops_training_within_loss_read_steps(tiny_cfg, tmp_path, monkeypatch):
    """The rasterizer reads the Gaussians back on one step in LOSS_READ (on a GPU each read is a
    wait) and the losses are read back every LOSS_READ steps: a NaN written into the offsets at
    step 30 (NaN means, culled by the rasterizer, whose NaN gradients make the decoders NaN, which
    then drop every Gaussian) stops the run at the read after it, naming the first NaN loss."""
    import lightning as L

    from segs.modules import gaussian_mapper
    from segs.train import build, step_batches

    checked: list[int] = []
    real = gaussian_mapper.rasterize

    def spy(*args, check_values=True, **kwargs):
        if check_values:
            checked.append(module.global_step)
        return real(*args, check_values=check_values, **kwargs)

    class Poison(L.Callback):
        def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
            if trainer.global_step == 30:
                with torch.no_grad():
                    pl_module.model.field.rows["offsets"].fill_(float("nan"))

    monkeypatch.setattr(gaussian_mapper, "rasterize", spy)
    steps = gaussian_mapper.LOSS_READ + 20
    cfg = tiny_cfg(f"trainer.max_steps={steps}", "callbacks.periodic_checkpoint.every_n_steps=0", "eval.enabled=false",
                   out=tmp_path / "poison")  # fmt: skip
    t = build(cfg)
    module = t.module
    t.trainer.callbacks.append(Poison())
    with pytest.raises(FloatingPointError, match="^training step 3[01]: the loss is nan"):
        t.trainer.fit(t.module, step_batches(steps))
    assert checked == [0]
    assert len(module.loss_history) == gaussian_mapper.LOSS_READ


def test_the_progress_bar_shows_the_loss_and_the_gaussians_of_the_last_written_step(tiny_cfg, tmp_path):
    from segs.callbacks import StepProgressBar
    from segs.train import build, step_batches

    cfg = tiny_cfg("trainer.max_steps=20", "trainer.log_every_n_steps=10", "callbacks.periodic_checkpoint.every_n_steps=0",
                   "eval.enabled=false", out=tmp_path / "bar")  # fmt: skip
    t = build(cfg)
    t.trainer.fit(t.module, step_batches(20))
    shown = StepProgressBar().get_metrics(t.trainer, t.module)
    assert float(shown["loss"]) == pytest.approx(t.module.loss_history[19], rel=1e-3)
    assert float(shown["gaussians"]) == t.module.model.counts()["gaussians"]


def test_the_progress_bar_switched_off_needs_no_callback_removed(tmp_path):
    """trainer.enable_progress_bar=false alone works: the bar's callback is left out (Lightning
    refuses a progress-bar callback with the bar off)."""
    from segs.config import compose
    from segs.train import build

    cfg = compose(["trainer.enable_progress_bar=false", "logger=none"], config_name="train", output_dir=str(tmp_path))
    assert cfg.callbacks.progress_bar is not None
    t = build(cfg)
    assert t.trainer.progress_bar_callback is None
