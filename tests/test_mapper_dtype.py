"""The mapper runs on the parameters' device and dtype: every row added by SLAM points, growth or
densification takes them (a float32 / CPU slip breaks float64 here and CUDA on a GPU)."""
from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch

from segs.config import model_node
from segs.data.frame import Camera
from segs.modules.config import build_model
from segs.modules.optim import make_adam
from segs.modules.scene_model import View

NO_CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
DEVICES = ["cpu", pytest.param("cuda", marks=[pytest.mark.cuda, NO_CUDA])]
CAMERA = Camera(fx=60.0, fy=60.0, cx=32.0, cy=24.0, width=64, height=48)


def _points(n: int, device: str) -> torch.Tensor:
    g = torch.Generator().manual_seed(0)
    xyz = torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5
    xyz[:, 2] += 2.0
    return xyz.to(device)


def _assert_rows(model: torch.nn.Module, opt, dtype: torch.dtype, device: str) -> None:
    """Every floating parameter, buffer and Adam moment has `dtype` and lives on `device`."""
    tensors = dict(model.named_parameters()) | dict(model.named_buffers())
    for name, t in tensors.items():
        assert t.device.type == device, name
        if t.is_floating_point():
            assert t.dtype == dtype, name
    for p, state in opt.state.items():
        for k, v in state.items():
            if torch.is_tensor(v) and v.shape == p.shape:
                assert v.dtype == dtype and v.device.type == device, k


def _fake_render(n: int, value: float, device: str, dtype=torch.float32) -> SimpleNamespace:
    """Rasterizer output of n Gaussians with screen-space gradient `value` (the rasterizer's float32)."""
    means2d = torch.zeros(n, 2, dtype=dtype, device=device, requires_grad=True)
    means2d.grad = torch.full((n, 2), value, dtype=dtype, device=device)
    return SimpleNamespace(image=torch.zeros(CAMERA.height, CAMERA.width, 3, device=device), means2d=means2d,
                           radii=torch.full((n,), 3, dtype=torch.int32, device=device))  # fmt: skip


@pytest.mark.parametrize("device", DEVICES)
def test_segs_anchors_grow_and_prune_in_float64(device):
    torch.manual_seed(0)
    densify = {"stats_from": 0, "grow_from": 0, "interval": 10, "grad_threshold": 1e-4, "min_opacity": 0.3}
    model = build_model(model_node("segs", k=4, feature_dim=8, hidden=8, voxel_size=0.01, min_new_points=1, densify=densify))
    model.to(device=device, dtype=torch.float64)
    added = model.add_points(_points(40, device), torch.rand(40, 3, dtype=torch.float64, device=device),
                             torch.arange(40, device=device) % 3, None)  # fmt: skip
    assert added > 0
    opt = make_adam(model.param_groups())
    with torch.no_grad():  # Gaussians away from their anchors, so that growth finds empty cells
        model.field.rows.offsets.normal_(0.0, 2.0)
    w2c = torch.eye(4, dtype=torch.float64, device=device)
    for step in range(1, 11):
        decoded = model.decode(View(w2c, CAMERA, 0), step)
        model.after_backward(decoded, _fake_render(len(decoded), 0.1, device), step)
    n0 = len(model.field)
    edits = model.maintain(10, opt)
    assert edits["grown"] > 0 and edits["pruned"] > 0, edits
    assert len(model.field) == n0 + edits["grown"] - edits["pruned"]
    _assert_rows(model, opt, torch.float64, device)
    T = torch.eye(4, device=device)  # a float32 loop correction applied to float64 anchors
    T[:3, 3] = 0.1
    assert model.correct_map({0: T}, opt) > 0
    _assert_rows(model, opt, torch.float64, device)


@pytest.mark.parametrize("device", DEVICES)
def test_plain_gaussians_clone_split_prune_in_float64(device):
    torch.manual_seed(0)
    densify = {"from_step": 0, "interval": 10, "grad_threshold": 1e-3, "percent_dense": 0.05, "min_opacity": 0.05,
               "opacity_reset_interval": 0}  # fmt: skip
    model = build_model(model_node("plain_3dgs", sh_degree=1, densify=densify))
    model.to(device=device, dtype=torch.float64)
    model.add_points(_points(30, device), torch.rand(30, 3, dtype=torch.float64, device=device), torch.arange(30, device=device), None)
    opt = make_adam(model.param_groups())
    with torch.no_grad():  # a third transparent (pruned), half of the rest large (split), half small (cloned)
        model.gs["opacities"][:10] = -10.0
        model.gs["log_scales"][10:20] = -1.0
        model.gs["log_scales"][20:] = -6.0
    decoded = model.decode(View(torch.eye(4, dtype=torch.float64, device=device), CAMERA), 1)
    model.after_backward(decoded, _fake_render(len(decoded), 1.0, device), 1)
    edits = model.maintain(10, opt)
    assert edits["cloned"] > 0 and edits["split"] > 0 and edits["pruned"] >= 10, edits
    _assert_rows(model, opt, torch.float64, device)
    T = torch.eye(4, device=device)
    T[:3, 3] = 0.1
    assert model.correct_map({25: T}, opt) > 0
    _assert_rows(model, opt, torch.float64, device)
