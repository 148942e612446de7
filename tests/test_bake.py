"""The exported map fitted to the views (segs.modules.bake) and its place in a run's results."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from plyfile import PlyData

from segs.data.frame import Camera
from segs.modules.bake import MIN_OPACITY, refine_cloud
from segs.modules.contract import GaussianCloud, TrainingView, to_uint8
from segs.modules.metrics import psnr
from segs.modules.scene_model import View
from segs.raster import rasterize

ROOT = Path(__file__).resolve().parents[1]
CAMERA = Camera(fx=60.0, fy=60.0, cx=31.5, cy=23.5, width=64, height=48)


def _render(gaussians, view: TrainingView) -> torch.Tensor:
    out = rasterize(*gaussians, view.w2c, View(view.w2c, view.camera).K, view.camera.width, view.camera.height,
                    background=torch.zeros(3), backend="cpu")  # fmt: skip
    return out.image


def _scene(seed: int = 0) -> tuple[GaussianCloud, list[TrainingView]]:
    """60 coloured Gaussians 2-3 m in front of four cameras 10 cm apart, and the views' images of them."""
    g = torch.Generator().manual_seed(seed)
    n = 60
    means = torch.cat([(torch.rand(n, 2, generator=g) - 0.5) * 2.0, 2.0 + torch.rand(n, 1, generator=g)], 1)
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1)
    scales = 0.05 + 0.1 * torch.rand(n, 3, generator=g)
    cloud = GaussianCloud(means, quats, scales, 0.3 + 0.6 * torch.rand(n, generator=g), torch.rand(n, 3, generator=g))
    views = []
    for i in range(4):
        w2c = torch.eye(4)
        w2c[0, 3] = 0.1 * i - 0.15
        view = TrainingView(kf_id=i, frame_index=i, timestamp=float(i), image=torch.zeros(48, 64, 3, dtype=torch.uint8), w2c=w2c,
                            camera=CAMERA)  # fmt: skip
        with torch.no_grad():
            view.image = to_uint8(_render((cloud.means, cloud.quats, cloud.scales, cloud.opacities, cloud.colors), view))
        views.append(view)
    return cloud, views


def _mean_psnr(cloud: GaussianCloud, views: list[TrainingView]) -> float:
    with torch.no_grad():
        return float(np.mean([psnr(_render((cloud.means, cloud.quats, cloud.scales, cloud.opacities, cloud.colors), v).clamp(0, 1), v.rgb())
                              for v in views]))  # fmt: skip


def test_fitting_brings_a_wrongly_coloured_cloud_to_the_views_images():
    truth, views = _scene()
    start = GaussianCloud(truth.means.clone(), truth.quats.clone(), truth.scales.clone(), torch.full_like(truth.opacities, 0.5),
                          torch.full_like(truth.colors, 0.5))  # fmt: skip
    kept = [t.clone() for t in (start.means, start.colors, start.opacities)]
    fitted = refine_cloud(start, views, 150, _render, scene_extent=1.0)
    before, after = _mean_psnr(start, views), _mean_psnr(fitted, views)
    assert after > before + 6.0, (before, after)
    assert all(torch.equal(a, b) for a, b in zip(kept, (start.means, start.colors, start.opacities)))  # the input is not changed
    assert fitted.means.dtype == torch.float32 and fitted.means.device.type == "cpu"
    assert torch.allclose(fitted.quats.norm(dim=-1), torch.ones(len(fitted)), atol=1e-5)


def test_fitting_drops_what_a_viewer_would_not_draw_and_zero_steps_change_nothing():
    truth, views = _scene(1)
    # a Gaussian far outside every view gets no gradient and keeps its opacity; one far below 1/255 is dropped
    means = torch.cat([truth.means, torch.tensor([[50.0, 0.0, 2.5], [0.0, 0.0, 2.5]])])
    opacities = torch.cat([truth.opacities, torch.tensor([0.9, 1e-4])])
    cloud = GaussianCloud(means, torch.cat([truth.quats, truth.quats[:2]]), torch.cat([truth.scales, truth.scales[:2]]), opacities,
                          torch.cat([truth.colors, truth.colors[:2]]))  # fmt: skip
    assert refine_cloud(cloud, views, 0, _render, 1.0) is cloud
    fitted = refine_cloud(cloud, views, 5, _render, 1.0)
    assert bool((fitted.opacities >= MIN_OPACITY).all())
    assert len(fitted) == len(cloud) - 1 and bool((fitted.means[:, 0] == 50.0).any())


def test_a_segs_run_writes_the_fitted_ply_and_scores_it(tiny_cfg, tmp_path):
    from segs.train import run

    cfg = tiny_cfg("trainer.max_steps=60", "eval.ply_fit_steps=150", "callbacks.periodic_checkpoint.every_n_steps=0", out=tmp_path / "fit")
    metrics = run(cfg)
    assert metrics["ply_gaussians"] == PlyData.read(str(tmp_path / "fit" / "point_cloud.ply"))["vertex"].count > 0
    assert json.loads((tmp_path / "fit" / "metrics.json").read_text())["ply_psnr"] == pytest.approx(metrics["ply_psnr"])
    # the same training, its first keyframe's decoding written as it is
    plain = run(tiny_cfg("trainer.max_steps=60", "eval.ply_fit_steps=0", "callbacks.periodic_checkpoint.every_n_steps=0",
                         out=tmp_path / "as_decoded"))  # fmt: skip
    assert metrics["ply_psnr"] > plain["ply_psnr"] + 1.5, (metrics["ply_psnr"], plain["ply_psnr"])
    assert metrics["psnr"] == pytest.approx(plain["psnr"], abs=0.5)  # the map itself: unchanged by the export
    # bench/ply_fit.py on the run folder (its config where `python -m segs.train` has Hydra write it):
    # the mapper rebuilt from the checkpoint writes the same PLYs
    (tmp_path / "fit" / ".hydra").mkdir()
    OmegaConf.save(cfg, tmp_path / "fit" / ".hydra" / "config.yaml")
    sys.path.insert(0, str(ROOT / "bench"))
    import ply_fit

    assert ply_fit.main([str(tmp_path / "fit"), "--steps", "150", "0", "--out", str(tmp_path / "ply_fit.json")]) == 0
    written = json.loads((tmp_path / "ply_fit.json").read_text())
    rows = written["rows"]
    # segs's own viewer, decoded for each test camera, draws what the map renders there
    assert written["camera_psnr"] == pytest.approx(metrics["psnr"], abs=0.2), (written["camera_psnr"], metrics["psnr"])
    assert [r["steps"] for r in rows] == [0, 150]
    assert rows[0]["psnr"] == pytest.approx(plain["ply_psnr"], abs=0.01) and rows[0]["gaussians"] == plain["ply_gaussians"]
    assert rows[1]["psnr"] == pytest.approx(metrics["ply_psnr"], abs=0.01) and rows[1]["gaussians"] == metrics["ply_gaussians"]


def test_a_plain_3dgs_run_writes_its_own_parameters_unscored(tiny_cfg, tmp_path):
    from segs.train import run

    metrics = run(tiny_cfg("+ablation=plain_3dgs", "trainer.max_steps=20", "callbacks.periodic_checkpoint.every_n_steps=0"))
    assert metrics["ply_psnr"] is None and metrics["ply_gaussians"] > 0
