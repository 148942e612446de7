"""segs.raster gradients: torch backend vs finite differences (float64), C++ projection vs torch."""
from __future__ import annotations

import pytest
import torch

from segs.raster import _cpu_backend, _projection, _torch_backend, available_backends, rasterize
from segs.raster.scenes import random_scene

needs_cpu = pytest.mark.skipif("cpu" not in available_backends(), reason="C++ backend unavailable")


@pytest.fixture(autouse=True)
def _one_torch_thread():
    """Small tensors: one thread is as fast and immune to a busy machine (OpenMP barriers)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def weighted(outputs, seed=0):
    """A scalar loss with fixed random weights: gradcheck then tests every input entry once."""
    flat = torch.cat([o.flatten() for o in outputs])
    w = torch.randn(flat.shape, generator=torch.Generator().manual_seed(seed), dtype=flat.dtype)
    return (w * flat).sum()


def tiny_scene(n=3, width=20, height=14, seed=0):
    """A few well-separated, semi-transparent Gaussians (no alpha clamp, no early stop)."""
    s = random_scene(n, width, height, seed=seed, dtype=torch.float64, scale_range=(0.08, 0.3))
    s.opacities = s.opacities.clamp(0.2, 0.8)
    return s


def test_torch_backend_matches_finite_differences():
    s = tiny_scene()
    bg = torch.tensor([0.2, 0.5, 0.7], dtype=torch.float64)
    inputs = [p.clone().requires_grad_(True) for p in s.params()] + [bg.requires_grad_(True)]

    def render(means, quats, scales, opacities, colors, background):
        r = rasterize(means, quats, scales, opacities, colors, s.viewmat, s.K, s.width, s.height,
                      background=background, backend="torch")
        return weighted([r.image, r.depth, r.alpha])

    with torch.no_grad():
        r = rasterize(*s.params(), s.viewmat, s.K, s.width, s.height, backend="torch")
    assert (r.radii > 0).all() and r.alpha.max() > 0.1
    assert torch.autograd.gradcheck(render, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


def test_torch_compositing_matches_finite_differences_in_screen_space():
    """d/d means2d (the densification signal) and d/d conics, opacities, colors, depths."""
    s = tiny_scene(n=4, seed=1)
    proj = _projection.project(s.means, s.quats, s.scales, s.viewmat, s.K, s.width, s.height,
                               0.01, 100.0)
    inputs = [t.detach().clone().requires_grad_(True)
              for t in (proj.means2d, proj.conics, s.colors, s.opacities, proj.depths)]
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)

    def composite(means2d, conics, colors, opacities, depths):
        out = _torch_backend.rasterize_pixels(means2d, conics, colors, opacities, depths,
                                              proj.radii, s.width, s.height, bg)
        return weighted(out)

    assert torch.autograd.gradcheck(composite, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


def _projection_inputs(n=400, seed=3):
    s = random_scene(n, 64, 48, seed=seed, scale_range=(0.01, 0.5))
    g = torch.Generator().manual_seed(seed)
    quats = s.quats * torch.empty(n, 1).uniform_(0.3, 3.0, generator=g)  # not unit
    R, t = s.viewmat[:3, :3], s.viewmat[:3, 3]
    cam = torch.randn(40, 3, generator=g) * torch.tensor([4.0, 4.0, 1.0]) + torch.tensor([0, 0, 2.0])
    cam[:5, 2] = -1.0  # behind the camera
    means = s.means.clone()
    means[:40] = (cam - t) @ R  # many outside the field of view: clamped Jacobian
    return means, quats, s.scales, s.viewmat, s.K


@needs_cpu
@pytest.mark.parametrize("eps2d", [0.3, 1.2])
def test_cpp_projection_matches_torch_projection(eps2d):
    means, quats, scales, viewmat, K = _projection_inputs()
    outs = {}
    for name, fn in (("cpu", _cpu_backend.project), ("torch", _projection.project)):
        params = [t.clone().requires_grad_(True) for t in (means, quats, scales)]
        p = fn(*params, viewmat, K, 64, 48, 0.01, 100.0, eps2d)
        g = torch.Generator().manual_seed(0)
        w = [torch.randn(t.shape, generator=g) for t in (p.means2d, p.conics, p.depths)]
        loss = sum((wi * ti).sum() for wi, ti in zip(w, (p.means2d, p.conics, p.depths)))
        loss.backward()
        outs[name] = (p, [t.grad for t in params])
    (pc, gc), (pt, gt) = outs["cpu"], outs["torch"]
    assert torch.equal(pc.radii, pt.radii) and (pt.radii == 0).sum() >= 5
    for a, b in zip(pc[:3], pt[:3]):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)
    for a, b in zip(gc, gt):
        err = (a - b).abs().max() / b.abs().max()
        assert err < 1e-4, err


@needs_cpu
def test_viewmat_gradient_uses_the_torch_projection():
    s = random_scene(50, 32, 24, seed=2, scale_range=(0.05, 0.3))
    viewmat = s.viewmat.clone().requires_grad_(True)
    r = rasterize(*s.params(), viewmat, s.K, 32, 24, backend="cpu")
    r.image.sum().backward()
    assert viewmat.grad is not None and viewmat.grad.abs().sum() > 0


@needs_cpu
def test_cpu_backward_is_bit_identical_from_run_to_run():
    # tiles are spread over the threads in a fixed order and the per-thread sums added in thread
    # order, so training is reproducible (a resumed run can end exactly as the uninterrupted one)
    torch.set_num_threads(2)  # the fixture restores the count
    s = random_scene(4000, 160, 120, seed=4, scale_range=(0.01, 0.08))
    bg = torch.tensor([0.1, 0.2, 0.3])
    grads = []
    for _ in range(5):
        inputs = [p.clone().requires_grad_(True) for p in s.params()] + [bg.clone().requires_grad_(True)]
        r = rasterize(*inputs[:5], s.viewmat, s.K, s.width, s.height, background=inputs[5], backend="cpu")
        weighted([r.image, r.depth, r.alpha]).backward()
        grads.append([x.grad for x in inputs])
    for g in grads[1:]:
        assert all(torch.equal(a, b) for a, b in zip(g, grads[0]))
