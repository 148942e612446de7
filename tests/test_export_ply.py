"""point_cloud.ply is in the standard 3D-GS layout (x y z nx ny nz f_dc_0..2 f_rest_* opacity
scale_0..2 rot_0..3; logit opacities, log scales, wxyz quaternions, channel-major f_rest) and
holds the map: read back with plyfile and rendered by segs.raster, it gives the model's image."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from plyfile import PlyData

from segs.modules.scene_model import View
from segs.modules.sh import C0, eval_sh
from segs.raster import rasterize
from segs.train import build, step_batches


def _trained(tiny_cfg, *overrides):
    cfg = tiny_cfg("trainer.max_steps=40", "callbacks.periodic_checkpoint.every_n_steps=0", "eval.enabled=false", *overrides)
    torch.manual_seed(0)
    t = build(cfg)
    module, trainer = t.module, t.trainer
    trainer.fit(module, step_batches(40))
    return module


def _layout(sh_degree: int) -> list[str]:
    rest = 3 * ((sh_degree + 1) ** 2 - 1)
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(rest)]
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])  # fmt: skip


def _render_ply(path, view: View, sh_degree: int, raster) -> torch.Tensor:
    """The PLY's Gaussians rasterized at view, colours from their SH as 3D-GS evaluates them."""
    v = PlyData.read(str(path))["vertex"]
    col = lambda names: torch.from_numpy(np.stack([np.asarray(v[n], np.float32) for n in names], 1))  # noqa: E731
    means = col(["x", "y", "z"])
    k = (sh_degree + 1) ** 2
    rest = means.new_zeros(len(means), 0, 3)
    if k > 1:  # channel-major in the file: f_rest_{c * (k-1) + j}
        rest = col([f"f_rest_{i}" for i in range(3 * (k - 1))]).reshape(-1, 3, k - 1).transpose(1, 2)
    sh = torch.cat([col(["f_dc_0", "f_dc_1", "f_dc_2"])[:, None], rest], 1)
    colors = eval_sh(sh_degree, sh, torch.nn.functional.normalize(means - view.center, dim=-1))
    out = rasterize(means, torch.nn.functional.normalize(col(["rot_0", "rot_1", "rot_2", "rot_3"]), dim=-1),
                    torch.exp(col(["scale_0", "scale_1", "scale_2"])), torch.sigmoid(col(["opacity"])[:, 0]), colors,
                    view.w2c, view.K, view.camera.width, view.camera.height, background=torch.tensor(raster.background),
                    near=raster.near, far=raster.far, backend=raster.backend)  # fmt: skip
    return out.image.clamp(0, 1)


@pytest.mark.parametrize("model, sh_degree", [("segs", 0), ("plain_3dgs", 3)])
def test_the_ply_renders_to_the_models_image(tiny_cfg, tmp_path, model, sh_degree):
    module = _trained(tiny_cfg, *(["+ablation=plain_3dgs"] if model == "plain_3dgs" else []))
    if model == "plain_3dgs":  # 40 steps leave the higher SH bands near 0: make their order matter
        with torch.no_grad():
            module.model.gs["sh_rest"].normal_(0.0, 0.2, generator=torch.Generator().manual_seed(0))
    path = tmp_path / "point_cloud.ply"
    n = module.export_ply(path)
    ply = PlyData.read(str(path))
    vertex = ply["vertex"]
    assert [p.name for p in vertex.properties] == _layout(sh_degree)
    assert all(p.val_dtype == "f4" for p in vertex.properties) and ply.elements[0].name == "vertex" and len(vertex) == n > 0
    assert C0 == pytest.approx(0.28209479177387814)
    first = module.first_view()
    view = View(first.w2c, first.camera, first.kf_id)
    got = _render_ply(path, view, sh_degree, module.raster)
    assert got.std() > 0.01  # a map, not a blank image
    # the model's Gaussians, every one (GaussianMapper.gaussians: what export_ply writes), rendered
    g, r = module.gaussians(), module.raster
    expected = rasterize(g.means, g.quats, g.scales, g.opacities, g.colors, view.w2c, view.K, first.camera.width, first.camera.height,
                         background=torch.tensor(r.background), near=r.near, far=r.far, backend=r.backend).image.clamp(0, 1)  # fmt: skip
    diff = (got - expected).abs()
    assert diff.max() < 2e-3 and diff.mean() < 1e-4, (float(diff.max()), float(diff.mean()))
    # the model's own render: the same for 3D-GS; SEGS culls the anchors outside the view frustum
    # (Scaffold-GS), whose Gaussians reach into the image border (tiny run: mean 0.005, max 0.07)
    own = (got - module.render_image(first.w2c, first.camera, first.kf_id)["image"]).abs()
    assert own.mean() < (1e-4 if model == "plain_3dgs" else 0.02), float(own.mean())
