"""Coarse-to-fine training resolution (segs.modules.resolution, mapping.num_downscales)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from segs.data.frame import Camera
from segs.errors import ConfigError
from segs.modules.config import mapping_config
from segs.modules.resolution import coarse_camera, coarse_depth, coarse_image, downscale_factor
from segs.modules.scene_model import View
from segs.raster import rasterize


def test_the_schedule_halves_the_divisor_after_each_phase():
    factors = [downscale_factor(s, 1000, 2, 0.1) for s in (0, 99, 100, 199, 200, 999)]
    assert factors == [4, 4, 2, 2, 1, 1]
    assert downscale_factor(0, 1000, 0, 0.1) == 1  # off
    assert downscale_factor(5, -1, 2, 0.1) == 1  # no step count known: full size


def test_coarse_intrinsics_project_where_the_block_mean_sits():
    cam = Camera(fx=500.0, fy=480.0, cx=319.5, cy=239.5, width=640, height=480)
    coarse = coarse_camera(cam, 4)
    assert (coarse.width, coarse.height) == (160, 120)
    p = np.array([0.3, -0.2, 2.0])
    u, v = (cam.K @ p)[:2] / p[2]
    uc, vc = (coarse.K @ p)[:2] / p[2]
    # OpenCV centres at integers: fine pixels 4j..4j+3 average into coarse pixel j
    assert uc == pytest.approx((u + 0.5) / 4 - 0.5) and vc == pytest.approx((v + 0.5) / 4 - 0.5)
    assert coarse_camera(cam, 1) is cam


def test_images_and_depth_are_block_means():
    img = torch.arange(6 * 8 * 3, dtype=torch.float32).reshape(6, 8, 3)
    out = coarse_image(img, 2)
    assert out.shape == (3, 4, 3)
    assert torch.allclose(out[1, 2], img[2:4, 4:6].reshape(-1, 3).mean(0))
    depth = torch.tensor([[1.0, 0.0, 0.0, 0.0], [3.0, 2.0, 0.0, 0.0]])
    d = coarse_depth(depth, 2)
    assert d.tolist() == [[2.0, 0.0]]  # the valid depths' mean; no valid depth -> 0


def test_a_coarse_render_matches_the_block_mean_of_the_full_render():
    torch.manual_seed(0)
    n = 60
    means = torch.rand(n, 3) * torch.tensor([1.6, 1.2, 0.0]) - torch.tensor([0.8, 0.6, -2.5])
    quats = torch.nn.functional.normalize(torch.randn(n, 4), dim=-1)
    scales = torch.full((n, 3), 0.3)
    opac, colors = torch.full((n,), 0.8), torch.rand(n, 3)
    cam = Camera(fx=80.0, fy=80.0, cx=47.5, cy=35.5, width=96, height=72)

    def render(camera):
        view = View(torch.eye(4), camera)
        return rasterize(means, quats, scales, opac, colors, view.w2c, view.K, camera.width, camera.height, backend="torch").image

    fine, coarse = render(cam), render(coarse_camera(cam, 4))
    pooled = coarse_image(fine, 4)
    assert coarse.shape == pooled.shape == (18, 24, 3)
    # smooth Gaussians (sigma ~ 2.4 coarse pixels): sampling at the block centre ~ the block mean
    err = (coarse - pooled).abs().mean()
    assert err < 0.015
    # the principal point scaled as cx / 4 (centres misplaced by 3/8 pixel) is clearly worse
    naive = render(replace(coarse_camera(cam, 4), cx=cam.cx / 4, cy=cam.cy / 4))
    assert (naive - pooled).abs().mean() > 2 * err


def test_bad_schedule_values_are_config_errors():
    base = {"view_budget": 2, "min_scene_extent": 0.5, "adam_eps": 1e-15, "min_schedule_steps": 0, "render_filter": "trained",
            "render_filter_decay": 0.95, "compile": False}
    with pytest.raises(ConfigError, match="mapping.num_downscales"):
        mapping_config({**base, "num_downscales": -1, "downscale_phase": 0.1})
    with pytest.raises(ConfigError, match="mapping.downscale_phase"):
        mapping_config({**base, "num_downscales": 2, "downscale_phase": 0.6})
    with pytest.raises(ConfigError, match="mapping.min_schedule_steps"):
        mapping_config({**base, "num_downscales": 2, "downscale_phase": 0.25, "min_schedule_steps": -1})
    with pytest.raises(ConfigError, match="mapping.render_filter='sharp'"):
        mapping_config({**base, "num_downscales": 2, "downscale_phase": 0.25, "render_filter": "sharp"})


def _resolutions(cfg, steps: int) -> list[tuple[int, int]]:
    """(width, height) of every training step's render in a run of `steps` steps."""
    from segs.train import build, step_batches

    t = build(cfg)
    module, trainer = t.module, t.trainer
    seen = []
    render = module.render

    def spy(view, step=None, **kwargs):
        seen.append((view.camera.width, view.camera.height))
        return render(view, step, **kwargs)

    module.render = spy
    trainer.fit(module, step_batches(steps))
    assert np.isfinite(module.loss_history).all() and len(module.loss_history) == steps
    return seen


@pytest.mark.parametrize("overrides,total", [(("trainer.max_steps=40",), 80), (("trainer.max_steps=120",), 120),
                                             (("trainer.max_steps=40", "mapping.num_downscales=0"), 40),
                                             (("trainer.max_steps=40", "mapping.min_schedule_steps=0"), 40)])  # fmt: skip
def test_the_schedule_is_the_run_or_the_coarse_to_fine_minimum(overrides, total):
    from segs.config import compose

    cfg = compose(["mapping.num_downscales=2", "mapping.min_schedule_steps=80", *overrides])
    assert cfg.model.total_steps == total


def test_a_run_shorter_than_the_minimum_schedule_stops_inside_its_phases(tiny_cfg):
    cfg = tiny_cfg("trainer.max_steps=40", "mapping.num_downscales=2", "mapping.downscale_phase=0.25", "mapping.min_schedule_steps=80",
                   "callbacks.periodic_checkpoint.every_n_steps=0", "eval.enabled=false")  # fmt: skip
    assert cfg.model.total_steps == 80
    assert _resolutions(cfg, 40) == [(24, 18)] * 20 + [(48, 36)] * 20  # 1/4 for 80/4 steps, 1/2 for the next 20: no full size


def test_training_runs_coarse_first_then_at_full_size(tiny_cfg):
    cfg = tiny_cfg("trainer.max_steps=40", "mapping.num_downscales=2", "mapping.downscale_phase=0.25", "mapping.min_schedule_steps=0",
                   "callbacks.periodic_checkpoint.every_n_steps=0", "eval.enabled=false")  # fmt: skip
    seen = _resolutions(cfg, 40)
    assert seen[:10] == [(24, 18)] * 10 and seen[10:20] == [(48, 36)] * 10 and seen[20:] == [(96, 72)] * 20


@pytest.mark.parametrize("render_filter,eps2d,lagged", [("trained", 0.3 * 2**2, 0.3 * 9.0), ("fixed", 0.3, 0.3)])
def test_renders_outside_training_see_the_pixels_the_map_was_trained_at(tiny_cfg, render_filter, eps2d, lagged):
    """A run stopped in its 1/2-size phase renders at full size through 3D-GS's 0.3 px^2 filter of
    those pixels (0.3 * 2^2 full-size px^2) with render_filter=trained; its checkpoint keeps the
    factor and the averaged pixel area (decision 041), which sets the filter where it is kept."""
    cfg = tiny_cfg("trainer.max_steps=40", "mapping.num_downscales=2", "mapping.downscale_phase=0.25", "mapping.min_schedule_steps=80",
                   f"mapping.render_filter={render_filter}", "eval.enabled=false")  # fmt: skip
    from segs.train import build

    module = build(cfg).module  # a fresh module: full size until a step or a checkpoint says otherwise
    assert module.render_eps2d() == pytest.approx(0.3)
    module.trained_factor = 2
    ckpt: dict = {"state_dict": {f"model.{k}": v for k, v in module.model.state_dict().items()}}
    module.on_save_checkpoint(ckpt)
    restored = build(cfg).module
    restored.on_load_checkpoint(ckpt)
    assert restored.trained_factor == 2 and restored.render_eps2d() == pytest.approx(eps2d)
    module.trained_area = 9.0  # right after a switch from 1/4 to 1/2 size
    module.on_save_checkpoint(ckpt)
    restored.on_load_checkpoint(ckpt)
    assert restored.trained_area == 9.0 and restored.render_eps2d() == pytest.approx(lagged)
    del ckpt["segs"]["trained_area"]  # a checkpoint from before the average: the latest step's factor
    restored.on_load_checkpoint(ckpt)
    assert restored.trained_area is None and restored.render_eps2d() == pytest.approx(eps2d)
    del ckpt["segs"]["trained_factor"]  # a checkpoint from before the factor was kept: full size
    restored.on_load_checkpoint(ckpt)
    assert restored.render_eps2d() == pytest.approx(0.3)


def test_the_trained_factor_is_the_last_steps_and_sets_the_evaluation_filter(tiny_cfg):
    cfg = tiny_cfg("trainer.max_steps=40", "mapping.num_downscales=2", "mapping.downscale_phase=0.25", "mapping.min_schedule_steps=80",
                   "callbacks.periodic_checkpoint.every_n_steps=0", "eval.enabled=false")  # fmt: skip
    from segs.train import build, step_batches

    t = build(cfg)
    t.trainer.fit(t.module, step_batches(40))
    assert t.module.trained_factor == 2
    seen = []
    render = t.module.render
    t.module.render = lambda view, step=None, **kw: seen.append(kw.get("eps2d")) or render(view, step, **kw)
    kf = t.module.views.sample()
    t.module.render_image(kf.w2c, kf.camera)
    area = None  # the pixel area of the steps, averaged with mapping.render_filter_decay (0.95)
    for step in range(40):
        f2 = t.module.resolution_factor(step) ** 2
        area = float(f2) if area is None else 0.95 * area + 0.05 * f2
    assert 1.2 < 0.3 * area < 0.3 * 16 and seen == [pytest.approx(0.3 * area)]
