"""Pure-PyTorch tile rasterizer: the readable reference (oracle) for the other backends.

Autograd differentiates everything. The algorithm is 3D-GS's, written tile by tile:

1. sort visible Gaussians by camera z, list for each 16x16 tile the Gaussians whose 3-sigma
   rectangle touches it (front to back);
2. per tile, per pixel: ``alpha = min(0.99, opacity * exp(-sigma))`` with
   ``sigma = 0.5 (a dx^2 + c dy^2) + b dx dy``; skip ``alpha < 1/255``; stop before the
   Gaussian that would bring the transmittance below 1e-4;
3. ``image = sum w_i c_i + T_final * background``, ``alpha = 1 - T_final``,
   ``depth = sum w_i z_i / max(alpha, 1e-10)`` (expected z) with ``w_i = alpha_i T_i``.

Gaussians of a tile are processed in chunks (``CHUNK``) with the transmittance carried over, so
the memory autograd keeps grows with the work done, and a tile stops once every pixel is done.
Large scenes are checkpointed per tile (see ``CHECKPOINT_PAIRS``).
"""
from __future__ import annotations

import math

import torch
from torch.utils.checkpoint import checkpoint

from ._projection import project  # noqa: F401  (this backend's projection)

TILE = 16
ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4
ALPHA_EPS = 1e-10  # expected depth divides by max(alpha, ALPHA_EPS)
CHUNK = 64
# Above this many listed pixel-Gaussian pairs, tiles are recomputed in backward (checkpoint)
# instead of keeping every intermediate: autograd would otherwise need tens of GB.
CHECKPOINT_PAIRS = 20_000_000


def tile_rects(means2d: torch.Tensor, radii: torch.Tensor, width: int, height: int):
    """Tiles touched by each Gaussian's 3-sigma square: (x0, x1, y0, y1) [N] int64, x1/y1 exclusive.

    Same arithmetic as gsplat's ``isect_tiles``: floor((u - r) / 16) .. ceil((u + r) / 16).
    """
    tw, th = math.ceil(width / TILE), math.ceil(height / TILE)
    r = radii.to(means2d.dtype)
    u, v = means2d[:, 0].detach(), means2d[:, 1].detach()
    x0 = torch.floor((u - r) / TILE).clamp(0, tw).long()
    x1 = torch.ceil((u + r) / TILE).clamp(0, tw).long()
    y0 = torch.floor((v - r) / TILE).clamp(0, th).long()
    y1 = torch.ceil((v + r) / TILE).clamp(0, th).long()
    return x0, x1, y0, y1


def bin_gaussians(means2d, depths, radii, width: int, height: int):
    """Intersections sorted by (tile, depth): returns (gauss_ids [I], tile_starts [n_tiles+1])."""
    tw, th = math.ceil(width / TILE), math.ceil(height / TILE)
    device = means2d.device
    visible = torch.nonzero(radii > 0).squeeze(1)
    order = visible[torch.argsort(depths.detach()[visible], stable=True)]
    x0, x1, y0, y1 = tile_rects(means2d[order], radii[order], width, height)
    counts = (x1 - x0) * (y1 - y0)
    gauss = torch.repeat_interleave(torch.arange(order.numel(), device=device), counts)
    first = torch.cumsum(counts, 0) - counts
    k = torch.arange(gauss.numel(), device=device) - first[gauss]  # index within the rectangle
    width_g = (x1 - x0)[gauss]
    tile = (y0[gauss] + k // width_g) * tw + x0[gauss] + k % width_g
    by_tile = torch.argsort(tile, stable=True)  # keeps depth order inside each tile
    tile_counts = torch.bincount(tile, minlength=tw * th)
    starts = torch.zeros(tw * th + 1, dtype=torch.long, device=device)
    starts[1:] = torch.cumsum(tile_counts, 0)
    return order[gauss[by_tile]], starts


def _composite_tile(px, py, means2d, conics, opacities, feats):
    """Front-to-back compositing of one tile.

    px, py [P] pixel centres; Gaussians (depth order): means2d [M,2], conics [M,3],
    opacities [M], feats [M,F]. Returns (accumulated feats [P,F], final transmittance [P]).
    """
    P = px.shape[0]
    T = torch.ones(P, dtype=px.dtype, device=px.device)
    done = torch.zeros(P, dtype=torch.bool, device=px.device)
    acc = torch.zeros(P, feats.shape[1], dtype=px.dtype, device=px.device)
    for s in range(0, means2d.shape[0], CHUNK):
        sl = slice(s, s + CHUNK)
        dx = means2d[sl, 0:1] - px[None, :]
        dy = means2d[sl, 1:2] - py[None, :]
        a, b, c = conics[sl].unbind(-1)
        sigma = 0.5 * (a[:, None] * dx * dx + c[:, None] * dy * dy) + b[:, None] * dx * dy
        alpha = torch.clamp(opacities[sl, None] * torch.exp(-sigma), max=ALPHA_MAX)
        alpha = torch.where((sigma >= 0) & (alpha >= ALPHA_MIN), alpha, torch.zeros_like(alpha))
        T_after = T * torch.cumprod(1 - alpha, dim=0)  # [k, P] transmittance behind each
        T_before = torch.cat([T[None], T_after[:-1]], dim=0)
        keep = (T_after >= T_MIN) & ~done
        w = torch.where(keep, alpha * T_before, torch.zeros_like(alpha))
        acc = acc + w.T @ feats[sl]
        T = T * torch.where(keep, 1 - alpha, torch.ones_like(alpha)).prod(dim=0)
        done = done | (T_after[-1] < T_MIN)
        if bool(done.all()):
            break
    return acc, T


def rasterize_pixels(means2d, conics, colors, opacities, depths, radii, width, height, background):
    """Composite projected Gaussians into (image [H,W,3], depth [H,W], alpha [H,W]).

    means2d [N,2], conics [N,3], colors [N,3], opacities [N], depths [N], radii [N] (0 = culled),
    background [3]. ``depth`` is the expected z, sum w_i z_i / max(alpha, 1e-10).
    """
    tw, th = math.ceil(width / TILE), math.ceil(height / TILE)
    ids, starts = bin_gaussians(means2d, depths, radii, width, height)
    feats = torch.cat([colors, depths[:, None]], dim=1)
    dtype, device = means2d.dtype, means2d.device
    lx = torch.arange(TILE, dtype=dtype, device=device).repeat(TILE) + 0.5
    ly = torch.arange(TILE, dtype=dtype, device=device).repeat_interleave(TILE) + 0.5
    needs_grad = torch.is_grad_enabled() and any(
        t.requires_grad for t in (means2d, conics, colors, opacities, depths)
    )
    recompute = needs_grad and ids.numel() * TILE * TILE > CHECKPOINT_PAIRS
    tiles = []
    for t in range(tw * th):
        px, py = lx + (t % tw) * TILE, ly + (t // tw) * TILE
        g = ids[starts[t] : starts[t + 1]]
        args = (px, py, means2d[g], conics[g], opacities[g], feats[g])
        if recompute:
            acc, T = checkpoint(_composite_tile, *args, use_reentrant=False)
        else:
            acc, T = _composite_tile(*args)
        rgb = acc[:, :3] + T[:, None] * background
        tiles.append(torch.cat([rgb, acc[:, 3:4], (1 - T)[:, None]], dim=1))
    out = torch.stack(tiles).reshape(th, tw, TILE, TILE, 5).permute(0, 2, 1, 3, 4)
    out = out.reshape(th * TILE, tw * TILE, 5)[:height, :width]
    alpha = out[..., 4]
    return out[..., :3], out[..., 3] / alpha.clamp(min=ALPHA_EPS), alpha
