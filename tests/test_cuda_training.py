"""Training and evaluation on a CUDA device with the gsplat backend (skipped without CUDA).

Checked on an H100 (docs/performance.md "GPU"): the model's buffers, grown anchors and Gaussians,
evaluation renders and the PLY export must all stay on the training device.
"""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from segs.raster import available_backends
from segs.train import run

pytestmark = pytest.mark.skipif("cuda" not in available_backends(), reason="needs CUDA and gsplat (pip install 'segs[gpu]')")


@pytest.mark.parametrize("model", ["segs", "plain_3dgs"])
def test_tiny_run_on_cuda_finishes(tiny_cfg, model):
    extra = ["+ablation=plain_3dgs"] if model == "plain_3dgs" else []
    cfg = tiny_cfg("raster.backend=cuda", "trainer.accelerator=gpu", "trainer.max_steps=120", *extra)
    run(cfg)
    m = json.loads((Path(cfg.paths.output_dir) / "metrics.json").read_text())
    assert m["status"] == "finished" and m["test_views"] > 0 and 5 < m["psnr"] < 60
    assert (Path(cfg.paths.output_dir) / "point_cloud.ply").stat().st_size > 0
