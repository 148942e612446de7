"""Coarse-to-fine training resolution: the first steps of a run render and compare at 1/2^n of
the image size, then at half of that, up to full resolution (as OpenSplat and nerfstudio's
splatfacto train by default: 1/4 for their first 3,000 of 30,000 steps, 1/2 for the next 3,000).

A coarser step costs less where the cost is per pixel (rasterizer, SSIM, FPR's FFTs) and the
same where it is per Gaussian (decoding, projection, Adam). Images are area-averaged over
factor x factor blocks (the last rows / columns that do not fill a block are dropped), and the
intrinsics follow exactly: with the rasterizer's pixel edges at integers, u' = u / factor.
"""
from __future__ import annotations

from dataclasses import replace

import torch
import torch.nn.functional as F

from segs.data.frame import Camera


def downscale_factor(step: int, total_steps: int, num_downscales: int, phase: float) -> int:
    """The image size divisor at `step`: 2^num_downscales for the first phase * total_steps
    steps, halved after each further phase, 1 from step num_downscales * phase * total_steps."""
    if num_downscales <= 0 or total_steps <= 0:
        return 1
    level = int(step // max(phase * total_steps, 1.0))
    return 2 ** max(num_downscales - level, 0)


def coarse_camera(camera: Camera, factor: int) -> Camera:
    """Intrinsics of the image area-averaged by factor: Camera.scaled of the image cropped to a
    multiple of factor (the crop drops right / bottom pixels, so the principal point stays)."""
    if factor == 1:
        return camera
    cropped = replace(camera, width=camera.width // factor * factor, height=camera.height // factor * factor)
    return cropped.scaled(factor)


def coarse_image(image: torch.Tensor, factor: int) -> torch.Tensor:
    """[H,W,C] -> [H//factor, W//factor, C], the mean of each factor x factor block."""
    if factor == 1:
        return image
    return F.avg_pool2d(image.permute(2, 0, 1)[None], factor)[0].permute(1, 2, 0).contiguous()


def coarse_depth(depth: torch.Tensor, factor: int) -> torch.Tensor:
    """[H,W] metres, 0 = invalid -> [H//factor, W//factor]: the mean of each block's valid
    depths, 0 where a block has none."""
    if factor == 1:
        return depth
    valid = (depth > 0).to(depth.dtype)
    total = F.avg_pool2d((depth * valid)[None, None], factor)[0, 0]
    count = F.avg_pool2d(valid[None, None], factor)[0, 0]
    return torch.where(count > 0, total / count.clamp_min(1e-12), torch.zeros_like(total))
