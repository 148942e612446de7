"""mapping.compile: the torch.compile forms of the per-step tensor code give the eager values and
gradients (CPU inductor here; the same graphs run as Triton kernels on a GPU)."""
import math

import pytest
import torch

from segs.data.frame import Camera
from segs.modules import losses
from segs.modules.anchors import AnchorField
from segs.modules.scene_model import View

SLOW = pytest.mark.slow  # each compilation takes seconds on two cores


def _field(n: int) -> AnchorField:
    torch.manual_seed(3)
    field = AnchorField(k=4, feature_dim=8, hidden=8, appearance_dim=4, use_distance=True, frustum_margin=0.15)
    xyz = torch.rand(n, 3) - 0.5
    xyz[:, 2] += 3.0
    xyz[:4, 2] = -3.0  # behind the camera
    field.add(xyz, torch.randn(n, 8), torch.randn(n, 6) * 0.3 - 2.0, torch.zeros(n, dtype=torch.long), None)
    field.rows["offsets"].data.normal_()
    return field


def _decode_and_grads(field: AnchorField, view: View, emb: torch.Tensor):
    decoded, info = field.decode(view, emb)
    outs = (decoded.means, decoded.quats, decoded.scales, decoded.opacities, decoded.colors)
    gen = torch.Generator().manual_seed(0)
    loss = sum((t * torch.randn(t.shape, generator=gen)).sum() for t in outs)
    params = [field.rows["features"], field.rows["offsets"], field.rows["log_scales"], *field.parameters()]
    params = list({id(p): p for p in params if p.requires_grad}.values())
    return outs, torch.autograd.grad(loss, params), info


@SLOW
def test_compiled_decoding_equals_eager_for_two_anchor_counts():
    cam = Camera(fx=50.0, fy=50.0, cx=32.0, cy=24.0, width=64, height=48)
    emb = torch.randn(4)
    for n in (30, 57):  # the second count reuses the dynamic-shape compilation
        field = _field(n)
        view = View(torch.eye(4), cam)
        eager, eager_grads, info = _decode_and_grads(field, view, emb)
        field.compile_decoding()
        got, got_grads, info_c = _decode_and_grads(field, view, emb)
        assert torch.equal(info.keep, info_c.keep) and len(got[0]) == len(eager[0]) > 0
        for a, b in zip(got, eager):
            assert torch.allclose(a, b, atol=1e-5), (a - b).abs().max()
        for a, b in zip(got_grads, eager_grads):
            assert torch.allclose(a, b, atol=1e-4, rtol=1e-4), (a - b).abs().max()


@SLOW
def test_compiled_photometric_loss_equals_eager():
    torch.manual_seed(4)
    gt = torch.rand(24, 32, 3, dtype=torch.float64)  # float64: the kornia path (a GPU's), not the CPU's fused kernel
    render = (gt + 0.1 * torch.randn_like(gt)).clamp(0, 1).requires_grad_(True)
    eager = losses.photometric(render, gt, 0.2)
    (g_eager,) = torch.autograd.grad(eager["photometric"], render)
    compiled = torch.compile(losses.photometric)
    got = compiled(render, gt, 0.2)
    (g_got,) = torch.autograd.grad(got["photometric"], render)
    for key in ("l1", "ssim", "photometric"):
        assert math.isclose(float(got[key]), float(eager[key]), rel_tol=1e-9, abs_tol=1e-12), key
    assert torch.allclose(g_got, g_eager, atol=1e-12)


@SLOW
def test_a_run_with_mapping_compile_true_trains_compiled_and_records_it(tiny_cfg):
    import json
    from pathlib import Path

    from segs.train import run as train

    cfg = tiny_cfg("trainer.max_steps=6", "mapping.compile=true", "callbacks.periodic_checkpoint.every_n_steps=0", "eval.write_ply=false")
    train(cfg)
    m = json.loads((Path(cfg.paths.output_dir) / "metrics.json").read_text())
    assert m["provenance"]["compiled_step_code"] is True
    assert m["iterations"] == 6 and m["psnr"] is not None


@SLOW
def test_compiled_decoding_does_not_recompile_when_the_rows_grow():
    torch._dynamo.reset()
    cam = Camera(fx=50.0, fy=50.0, cx=32.0, cy=24.0, width=64, height=48)
    field, emb, view = _field(30), torch.randn(4), View(torch.eye(4), cam)
    field.compile_decoding()
    _decode_and_grads(field, view, emb)  # compiles for any anchor count
    with torch._dynamo.config.patch(error_on_recompile=True):
        for n in (7, 12):  # growth replaces every row with a longer one
            xyz = torch.rand(n, 3) - 0.5
            xyz[:, 2] += 3.0
            field.add(xyz, torch.randn(n, 8), torch.randn(n, 6) * 0.3 - 2.0, torch.zeros(n, dtype=torch.long), None)
            outs, grads, info = _decode_and_grads(field, View(torch.eye(4), cam), emb)
            assert len(info.visible) > 30 and all(torch.isfinite(g).all() for g in grads)


def test_where_torch_compile_cannot_build_null_runs_eager_and_true_is_a_config_error(tiny_cfg, monkeypatch, tmp_path):
    from segs.errors import ConfigError
    from segs.modules import gaussian_mapper
    from segs.train import build, step_batches

    monkeypatch.delenv("CXX", raising=False)
    monkeypatch.setattr(gaussian_mapper.shutil, "which", lambda name: None)  # no C++ compiler
    assert "no C++ compiler" in gaussian_mapper.compile_unavailable(torch.device("cpu"))
    monkeypatch.setattr(gaussian_mapper.importlib.util, "find_spec", lambda name: None)
    assert "Triton is not installed" in gaussian_mapper.compile_unavailable(torch.device("cuda"))
    t = build(tiny_cfg("trainer.max_steps=2", "mapping.compile=true", "eval.enabled=false", out=tmp_path / "a"))
    with pytest.raises(ConfigError, match="mapping.compile=true: no C\\+\\+ compiler"):
        t.trainer.fit(t.module, step_batches(2))
    t = build(tiny_cfg("trainer.max_steps=2", "eval.enabled=false", out=tmp_path / "b"))  # null on the CPU: eager, nothing checked
    t.trainer.fit(t.module, step_batches(2))
    assert t.module.compiled is False
