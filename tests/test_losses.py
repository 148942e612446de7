"""The fast loss kernels equal their definitions: SSIM against kornia.metrics.ssim, FPR's
half-spectrum form against the full centred spectrum, in value and in gradient."""
from __future__ import annotations

import kornia
import pytest
import torch

from segs.modules import fpr, losses
from segs.raster import fused_ssim, fused_ssim_available


def _pair(h: int, w: int, c: int = 3, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    gt = torch.rand(h, w, c, generator=g, dtype=torch.float64)
    render = (gt + 0.2 * torch.randn(h, w, c, generator=g, dtype=torch.float64)).clamp(0, 1)
    return render.requires_grad_(), gt


@pytest.mark.parametrize("size", [(32, 48), (31, 17), (120, 160)])
def test_ssim_equals_kornia_in_value_and_gradient(size):
    render, gt = _pair(*size)
    ours = losses.ssim(render, gt)
    (g_ours,) = torch.autograd.grad(ours, render)
    ref = kornia.metrics.ssim(losses.to_bchw(render), losses.to_bchw(gt), 11, max_val=1.0).mean()
    (g_ref,) = torch.autograd.grad(ref, render)
    assert float(ours.detach()) == pytest.approx(float(ref.detach()), abs=1e-12)
    assert torch.allclose(g_ours, g_ref, rtol=1e-9, atol=1e-15)


@pytest.mark.parametrize("size", [(6, 7), (31, 17), (120, 160)])
def test_fused_ssim_equals_kornia_in_value_and_gradient(size):
    render64, gt64 = _pair(*size, seed=2)
    render = render64.detach().float().requires_grad_()
    if not fused_ssim_available(render.permute(2, 0, 1), 11):
        pytest.skip("the C++ kernels cannot be built here")
    window = kornia.filters.get_gaussian_kernel1d(11, 1.5).flatten()
    ours = fused_ssim(render.permute(2, 0, 1), gt64.float().permute(2, 0, 1), window, 0.01**2, 0.03**2)  # non-contiguous views
    (g_ours,) = torch.autograd.grad(3.0 * ours, render)
    ref = kornia.metrics.ssim(losses.to_bchw(render64), losses.to_bchw(gt64), 11, max_val=1.0).mean()
    (g_ref,) = torch.autograd.grad(3.0 * ref, render64)
    assert float(ours.detach()) == pytest.approx(float(ref.detach()), abs=1e-6)
    assert float((g_ours.double() - g_ref).abs().max()) < 1e-5 * float(g_ref.abs().max())


def test_loss_ssim_takes_the_fused_kernel_on_cpu_float32_and_kornia_otherwise(monkeypatch):
    render64, gt64 = _pair(40, 48, seed=3)
    render, gt = render64.detach().float(), gt64.float()
    if not fused_ssim_available(render.permute(2, 0, 1), 11):
        pytest.skip("the C++ kernels cannot be built here")
    fused = float(losses.ssim(render, gt))
    monkeypatch.setenv("SEGS_RASTER_NO_CPU", "1")
    assert not fused_ssim_available(render.permute(2, 0, 1), 11)
    assert float(losses.ssim(render, gt)) == pytest.approx(fused, abs=1e-6)
    with pytest.raises(ValueError, match="one shape"):
        fused_ssim(render.permute(2, 0, 1), gt[:-1].permute(2, 0, 1), torch.ones(3) / 3, 0.01**2, 0.03**2)


@pytest.mark.parametrize("taps", [3, 7, 11])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_gaussian_window_is_kornias_to_the_bit(taps, dtype):
    ours = losses.gaussian_window(taps, 1.5, torch.zeros(1, dtype=dtype))
    ref = kornia.filters.get_gaussian_kernel1d(taps, 1.5, dtype=dtype).flatten()
    assert ours.dtype == dtype and ours.shape == (taps,)
    assert torch.equal(ours, ref)


def test_ssim_of_identical_images_is_one():
    _, gt = _pair(40, 40)
    assert float(losses.ssim(gt, gt)) == pytest.approx(1.0, abs=1e-9)


@pytest.mark.parametrize("mode", fpr.MODES)
@pytest.mark.parametrize("size", [(8, 8), (7, 9), (24, 32), (25, 31), (60, 80)])
def test_half_spectrum_fpr_equals_full_spectrum_definition(mode, size):
    render, gt = _pair(*size, seed=1)
    r, g = render.permute(2, 0, 1), gt.permute(2, 0, 1)
    fast = fpr.frequency_loss(r, g, mode)
    ref = fpr.reference_frequency_loss(r, g, mode)
    assert float(fast.detach()) == pytest.approx(float(ref.detach()), rel=1e-10, abs=1e-12)
    if float(ref.detach()) > 0:
        (g_fast,) = torch.autograd.grad(fast, render)
        (g_ref,) = torch.autograd.grad(ref, render)
        assert torch.allclose(g_fast, g_ref, rtol=1e-7, atol=1e-12)


def test_half_weights_count_every_masked_entry_once():
    for h, w in [(8, 8), (7, 9), (240, 320)]:
        for kind, ratio in [("high", 0.4), ("low", 0.1)]:
            full = (fpr.highpass_mask if kind == "high" else fpr.lowpass_mask)(h, w, ratio)
            assert float(fpr.half_weights(kind, h, w, ratio, "cpu").sum()) == float(full.sum())


def test_depth_l1_is_the_mean_over_valid_pixels_without_indexing():
    from segs.modules.losses import depth_l1

    g = torch.Generator().manual_seed(0)
    depth = torch.rand(12, 16, generator=g, requires_grad=True)
    gt = torch.rand(12, 16, generator=g) * (torch.rand(12, 16, generator=g) > 0.4)
    valid = gt > 0
    expected = (depth[valid] - gt[valid]).abs().mean()
    assert torch.allclose(depth_l1(depth, gt), expected)
    none = depth_l1(depth, torch.zeros(12, 16))
    assert float(none) == 0.0 and none.requires_grad
