"""Image metrics of the paper's protocol: PSNR, SSIM (the fused kernel of segs.raster on the
CPU, torchmetrics elsewhere) and LPIPS (AlexNet, v0.1).

LPIPS uses torchmetrics' implementation (its bundled linear-layer weights) with the AlexNet
backbone loaded from a weights file named in the config (torchvision's alexnet-owt-7be5be79.pth
state dict); torchvision itself is not installed. Without a file, LPIPS is unavailable and
reported as None ("n/a"); it is never computed from random weights.
"""
from __future__ import annotations

import logging
from pathlib import Path

import torch
from torch import nn
from torchmetrics.functional.image import structural_similarity_index_measure

from segs.errors import ConfigError
from segs.raster import fused_ssim, fused_ssim_available

SSIM_WINDOW = 11

log = logging.getLogger(__name__)


def psnr(render: torch.Tensor, gt: torch.Tensor) -> float:
    """Mean over channels of 20 log10(1 / sqrt(MSE_c)); [H,W,3] images in [0,1]."""
    return float(psnr_tensor(render, gt))


def psnr_tensor(render: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """`psnr` as a 0-d tensor on the images' device (no read back)."""
    mse = ((render.clamp(0, 1) - gt) ** 2).reshape(-1, render.shape[-1]).mean(0).clamp_min(1e-12)
    return (20.0 * torch.log10(1.0 / torch.sqrt(mse))).mean()


def ssim(render: torch.Tensor, gt: torch.Tensor) -> float:
    """SSIM with an 11x11 Gaussian window, sigma 1.5, data range 1, reflect border; [H,W,3] images.

    On the CPU in float32 the fused C++ kernel of segs.raster (the SSIM loss's) computes it in one
    pass: within 1.1e-5 of torchmetrics in float64 on the sample's frames, where torchmetrics in
    float32 is within 2.3e-5, and with no [5,3,H,W] stacked convolution (torchmetrics' raised the
    peak memory of an evaluation by 60-80 MB at 320x240 and 170-220 MB at 640x480). Elsewhere
    (CUDA) torchmetrics' structural_similarity_index_measure, the same definition."""
    a = render.detach().clamp(0, 1).permute(2, 0, 1).float().contiguous()
    b = gt.detach().permute(2, 0, 1).float().contiguous()
    if fused_ssim_available(a, SSIM_WINDOW):
        return float(fused_ssim(a, b, _gaussian_window(SSIM_WINDOW, 1.5), 0.01**2, 0.03**2))
    return float(structural_similarity_index_measure(a[None], b[None], gaussian_kernel=True, sigma=1.5, kernel_size=SSIM_WINDOW,
                                                     data_range=1.0))  # fmt: skip


def _gaussian_window(taps: int, sigma: float) -> torch.Tensor:
    """[taps] normalised Gaussian weights (torchmetrics' _gaussian)."""
    x = torch.arange(taps, dtype=torch.float32) - (taps - 1) / 2
    w = torch.exp(-((x / sigma) ** 2) / 2)
    return w / w.sum()


def alexnet_features() -> nn.Sequential:
    """The layer stack of torchvision's AlexNet `features` (indices match its state-dict keys)."""
    return nn.Sequential(
        nn.Conv2d(3, 64, 11, 4, 2), nn.ReLU(inplace=True), nn.MaxPool2d(3, 2),
        nn.Conv2d(64, 192, 5, padding=2), nn.ReLU(inplace=True), nn.MaxPool2d(3, 2),
        nn.Conv2d(192, 384, 3, padding=1), nn.ReLU(inplace=True),
        nn.Conv2d(384, 256, 3, padding=1), nn.ReLU(inplace=True),
        nn.Conv2d(256, 256, 3, padding=1), nn.ReLU(inplace=True), nn.MaxPool2d(3, 2),
    )  # fmt: skip


def _load_backbone(path: Path) -> nn.Sequential:
    if not path.is_file():
        raise ConfigError(f"eval.lpips_weights: file not found: {path}")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # corrupt or foreign file
        raise ConfigError(f"eval.lpips_weights: cannot read {path}: {type(err).__name__}") from None
    state = state.get("state_dict", state)
    feats = {k.removeprefix("features."): v for k, v in state.items() if k.startswith("features.")} or state
    net = alexnet_features()
    try:
        net.load_state_dict(feats, strict=True)
    except RuntimeError:
        raise ConfigError(f"eval.lpips_weights: {path} is not an AlexNet (torchvision) state dict") from None
    return net


class Lpips:
    """LPIPS (AlexNet, v0.1) on [H,W,3] images in [0,1], from a backbone weights file."""

    def __init__(self, weights: str | Path):
        import torchmetrics.functional.image.lpips as tm_lpips

        backbone = _load_backbone(Path(weights))
        original = tm_lpips._get_tv_model_features
        tm_lpips._get_tv_model_features = lambda net, pretrained=False: backbone
        try:
            self.net = tm_lpips._LPIPS(pretrained=True, net="alex").eval()
        finally:
            tm_lpips._get_tv_model_features = original

    @torch.no_grad()
    def __call__(self, render: torch.Tensor, gt: torch.Tensor) -> float:
        a = render.clamp(0, 1).permute(2, 0, 1)[None].float()
        b = gt.permute(2, 0, 1)[None].float()
        return float(self.net(a, b, normalize=True).mean())


def make_lpips(weights: str | None) -> Lpips | None:
    """Lpips from the configured file, or None (with one warning) when no file is configured."""
    if not weights:
        log.warning("LPIPS: no AlexNet weights file configured (eval.lpips_weights); LPIPS reported as n/a")
        return None
    return Lpips(weights)
