"""Anchor growing and pruning (the Scaffold-GS rule, as in the SEGS reference implementation).

Statistics (inside the statistics window): per neural Gaussian the norm of its screen-space
gradient (in NDC units: pixel gradient * (W/2, H/2)) and a visit count; per anchor the summed
opacity of its k Gaussians and a visit count.
Every `interval` steps inside the growth window:
- growing: the average gradient of Gaussians seen more than interval * success * 0.5 times; for
  level m = 0..depth-1 the threshold is tau * 2^m, the cell size eps * init_factor / factor^m,
  and candidates also pass rand > 0.5^(m+1); new anchors are the unique cell centres of
  candidate Gaussian positions whose cell holds no anchor yet; their feature is the max of the
  parents' features, log-scales log(cell size), offsets 0;
- pruning: anchors with accumulated opacity < min_opacity * visits once visits > interval *
  success are removed; anchors past that visit count restart their statistics.
"""
from __future__ import annotations

import math

import torch
from torch import nn

from segs.modules.anchors import AnchorField, DecodeInfo
from segs.modules.sepm import voxelize


class AnchorDensifier(nn.Module):
    """Densification statistics (buffers aligned with the anchors) and the grow / prune step."""

    def __init__(self, k: int, voxel_size: float, grad_threshold: float = 2e-4, update_depth: int = 3,
                 init_factor: int = 16, hierarchy_factor: int = 4, min_opacity: float = 0.005,
                 success_threshold: float = 0.8, max_anchors: int = 200_000):  # fmt: skip
        super().__init__()
        self.k, self.voxel_size, self.grad_threshold = k, voxel_size, grad_threshold
        self.update_depth, self.init_factor, self.hierarchy_factor = update_depth, init_factor, hierarchy_factor
        self.min_opacity, self.success_threshold, self.max_anchors = min_opacity, success_threshold, max_anchors
        self.register_buffer("opacity_accum", torch.zeros(0))
        self.register_buffer("anchor_visits", torch.zeros(0))
        self.register_buffer("grad_accum", torch.zeros(0, k))
        self.register_buffer("grad_visits", torch.zeros(0, k))

    def extend(self, m: int) -> None:
        z = self.opacity_accum.new_zeros
        self.opacity_accum = torch.cat([self.opacity_accum, z(m)])
        self.anchor_visits = torch.cat([self.anchor_visits, z(m)])
        self.grad_accum = torch.cat([self.grad_accum, z(m, self.k)])
        self.grad_visits = torch.cat([self.grad_visits, z(m, self.k)])

    def keep(self, mask: torch.Tensor) -> None:
        for name in ("opacity_accum", "anchor_visits", "grad_accum", "grad_visits"):
            setattr(self, name, getattr(self, name)[mask])

    def resize_(self, n: int) -> None:
        z = self.opacity_accum.new_zeros
        self.opacity_accum, self.anchor_visits = z(n), z(n)
        self.grad_accum, self.grad_visits = z(n, self.k), z(n, self.k)

    @torch.no_grad()
    def record(self, info: DecodeInfo, means2d_grad: torch.Tensor | None, radii: torch.Tensor, width: int, height: int) -> None:
        """Accumulate one view's statistics; means2d_grad [M,2] and radii [M] of the rendered Gaussians."""
        vis = info.visible
        self.opacity_accum[vis] += info.opacity.clamp_min(0).sum(1)
        self.anchor_visits[vis] += 1
        if means2d_grad is None or vis.numel() == 0:
            return
        slots = info.slots(self.k)
        drawn = radii > 0
        ndc = means2d_grad.new_tensor([width / 2.0, height / 2.0])
        norm = (means2d_grad[drawn] * ndc).norm(dim=-1).to(self.grad_accum)
        self.grad_accum.view(-1).index_add_(0, slots[drawn], norm)
        self.grad_visits.view(-1).index_add_(0, slots[drawn], torch.ones_like(norm))

    @torch.no_grad()
    def adjust(self, field: AnchorField, tags: torch.Tensor, interval: int, optimizer, generator: torch.Generator | None = None) -> tuple[dict, torch.Tensor]:
        """Grow then prune; returns (log numbers, kf tags of the surviving anchors)."""
        seen = self.grad_visits > interval * self.success_threshold * 0.5
        grads = self.grad_accum / self.grad_visits.clamp_min(1.0)
        grown, tags = self._grow(field, tags, grads, seen, optimizer, generator)
        self.grad_accum[: seen.shape[0]][seen] = 0.0
        self.grad_visits[: seen.shape[0]][seen] = 0.0
        pruned, tags = self._prune(field, tags, interval, optimizer)
        return {"grown": grown, "pruned": pruned, "anchors": len(field)}, tags

    def _grow(self, field, tags, grads, seen, optimizer, generator) -> tuple[int, torch.Tensor]:
        n0 = len(field)
        positions = field.gaussian_positions()  # [N,k,3] of the anchors before growing
        parent_of_slot = torch.arange(n0, device=positions.device).unsqueeze(1).expand(n0, self.k)
        total = 0
        for m in range(self.update_depth):
            room = self.max_anchors - len(field)
            if room <= 0:
                break
            size = self.voxel_size * self.init_factor / self.hierarchy_factor**m
            rand = torch.rand(grads.shape, generator=generator, device=grads.device)
            cand = seen & (grads >= self.grad_threshold * 2**m) & (rand > 0.5 ** (m + 1))
            if not bool(cand.any()):
                continue
            centres, cell = voxelize(positions[cand], size, existing=field.xyz)
            if centres.shape[0] == 0:
                continue
            parents = parent_of_slot[cand]
            ok = cell >= 0
            feats = centres.new_full((centres.shape[0], field.feature_dim), -math.inf)
            feats = feats.scatter_reduce(0, cell[ok, None].expand(-1, field.feature_dim), field.params["features"].detach()[parents[ok]], reduce="amax")
            new_tags = torch.zeros(centres.shape[0], dtype=tags.dtype, device=tags.device).scatter_(0, cell[ok], tags[parents[ok]])
            if centres.shape[0] > room:  # anchor cap: keep the cells with the strongest gradient
                strength = grads.new_zeros(centres.shape[0]).scatter_reduce(0, cell[ok], grads[cand][ok], reduce="amax")
                top = torch.argsort(strength, descending=True)[:room]
                centres, feats, new_tags = centres[top], feats[top], new_tags[top]
            field.add(centres, feats, centres.new_full((centres.shape[0], 6), math.log(size)), optimizer)
            self.extend(centres.shape[0])
            tags = torch.cat([tags, new_tags])
            total += centres.shape[0]
        return total, tags

    def _prune(self, field, tags, interval, optimizer) -> tuple[int, torch.Tensor]:
        enough = self.anchor_visits > interval * self.success_threshold
        prune = (self.opacity_accum < self.min_opacity * self.anchor_visits) & enough
        self.opacity_accum[enough] = 0.0
        self.anchor_visits[enough] = 0.0
        if not bool(prune.any()):
            return 0, tags
        keep = ~prune
        field.keep(keep, optimizer)
        self.keep(keep)
        return int(prune.sum()), tags[keep]
