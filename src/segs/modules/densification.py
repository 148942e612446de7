"""Densification strategies, stateless dataclasses in gsplat's style (their statistics are rows
of the primitives' store, segs.modules.rows): `record(...)` after each backward, `adjust(...)`
grows / prunes rows, Adam moments and statistics together.

AnchorGrowth: anchor growing and pruning (the Scaffold-GS rule, as in the SEGS reference
implementation).

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

AdaptiveDensity: plain 3D-GS (Kerbl et al. 2023): Gaussians with a large average screen-space
gradient are cloned (small) or split in two (large, children scaled by 1/1.6 and drawn from the
parent); transparent ones, and after the first opacity reset too large ones, are pruned.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from segs.modules.anchors import AnchorField, DecodeInfo
from segs.modules.geometry import quat_to_rotmat
from segs.modules.rows import PrimitiveRows
from segs.modules.sepm import voxelize


@dataclass
class AnchorGrowth:
    """The SEGS strategy (stateless: its statistics are rows of the anchor store).

    Windows in reference-run steps: statistics from `stats_from`, grow / prune rounds every
    `interval` steps (scaled with the run when `scale_interval`) from `grow_from`, both until `until`.
    """

    stats_from: int
    grow_from: int
    until: int
    interval: int
    scale_interval: bool
    grad_threshold: float
    update_depth: int
    init_factor: int
    hierarchy_factor: int
    min_opacity: float
    success_threshold: float

    @torch.no_grad()
    def record(self, field: AnchorField, info: DecodeInfo, means2d_grad: torch.Tensor | None, radii: torch.Tensor,
               width: int, height: int) -> None:  # fmt: skip
        """Accumulate one view's statistics; means2d_grad [M,2] and radii [M] of the rendered Gaussians."""
        rows, vis = field.rows, info.visible
        opacity = info.opacity.clamp_min(0).sum(1).to(rows.opacity_accum)
        rows.opacity_accum.index_add_(0, vis, opacity)  # vis is unique: the same as [vis] +=, faster
        rows.anchor_visits.index_add_(0, vis, torch.ones_like(opacity).to(rows.anchor_visits))
        if means2d_grad is None or vis.numel() == 0:
            return
        slots = info.slots(field.k)
        # every rendered slot is added, the undrawn ones (radius 0) as zeros: masked values, not
        # t[drawn], so that no data-dependent shape makes a GPU wait (the same sums)
        drawn = radii > 0
        g = means2d_grad
        norm = torch.stack([g[:, 0] * (width / 2.0), g[:, 1] * (height / 2.0)], -1).norm(dim=-1).to(rows.grad_accum)
        norm = torch.where(drawn, norm, torch.zeros_like(norm))
        rows.grad_accum.view(-1).index_add_(0, slots, norm)
        rows.grad_visits.view(-1).index_add_(0, slots, drawn.to(norm))

    @torch.no_grad()
    def adjust(self, field: AnchorField, optimizer, interval: int, voxel_size: float, max_anchors: int,
               generator: torch.Generator | None = None) -> dict:  # fmt: skip
        """Grow then prune (rows, moments and statistics together); returns numbers to log."""
        rows = field.rows
        seen = rows.grad_visits > interval * self.success_threshold * 0.5
        grads = rows.grad_accum / rows.grad_visits.clamp_min(1.0)
        grown = self._grow(field, grads, seen, optimizer, voxel_size, max_anchors, generator)
        rows.grad_accum[: seen.shape[0]][seen] = 0.0
        rows.grad_visits[: seen.shape[0]][seen] = 0.0
        pruned = self._prune(field, interval, optimizer)
        return {"grown": grown, "pruned": pruned, "anchors": len(field)}

    def _grow(self, field, grads, seen, optimizer, voxel_size, max_anchors, generator) -> int:
        n0, k = len(field), field.k
        positions = field.gaussian_positions()  # [N,k,3] of the anchors before growing
        parent_of_slot = torch.arange(n0, device=positions.device).unsqueeze(1).expand(n0, k)
        features, tags = field.rows.features.detach()[:n0], field.rows.kf_tag[:n0]
        total = 0
        for m in range(self.update_depth):
            room = max_anchors - len(field)
            if room <= 0:
                break
            size = voxel_size * self.init_factor / self.hierarchy_factor**m
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
            feats = feats.scatter_reduce(0, cell[ok, None].expand(-1, field.feature_dim), features[parents[ok]].to(feats), reduce="amax")
            new_tags = tags.new_zeros(centres.shape[0]).scatter_(0, cell[ok], tags[parents[ok]])
            if centres.shape[0] > room:  # anchor cap: keep the cells with the strongest gradient
                strength = grads.new_zeros(centres.shape[0]).scatter_reduce(0, cell[ok], grads[cand][ok], reduce="amax")
                top = torch.argsort(strength, descending=True)[:room]
                centres, feats, new_tags = centres[top], feats[top], new_tags[top]
            total += field.add(centres, feats, centres.new_full((centres.shape[0], 6), math.log(size)), new_tags, optimizer)
        return total

    def _prune(self, field, interval, optimizer) -> int:
        rows = field.rows
        enough = rows.anchor_visits > interval * self.success_threshold
        prune = (rows.opacity_accum < self.min_opacity * rows.anchor_visits) & enough
        rows.opacity_accum[enough] = 0.0
        rows.anchor_visits[enough] = 0.0
        if not bool(prune.any()):
            return 0
        rows.keep(~prune, optimizer)
        return int(prune.sum())


@dataclass
class AdaptiveDensity:
    """The plain 3D-GS strategy (stateless: statistics grad_accum, grad_count, max_radii are rows
    of the Gaussians' store). Windows in reference-run steps, as AnchorGrowth's."""

    from_step: int
    until_step: int
    interval: int
    scale_interval: bool
    grad_threshold: float
    percent_dense: float
    opacity_reset_interval: int
    min_opacity: float
    max_screen_radius: float

    @torch.no_grad()
    def record(self, rows: PrimitiveRows, means2d_grad: torch.Tensor | None, radii: torch.Tensor, width: int, height: int) -> None:
        """Accumulate one view: means2d_grad [N,2] and radii [N] of every Gaussian (None: no gradient)."""
        if means2d_grad is None or means2d_grad.shape[0] != len(rows):
            return
        visible = radii > 0
        ndc = means2d_grad * means2d_grad.new_tensor([width / 2.0, height / 2.0])
        rows.grad_accum[visible] += ndc[visible].norm(dim=-1).to(rows.grad_accum)
        rows.grad_count[visible] += 1
        rows.max_radii[visible] = torch.maximum(rows.max_radii[visible], radii[visible].to(rows.max_radii))

    @torch.no_grad()
    def adjust(self, rows: PrimitiveRows, optimizer, scene_extent: float, max_gaussians: int, prune_big: bool) -> dict:
        """Clone / split / prune; statistics restart. Returns {"cloned", "split", "pruned"}."""
        grads = rows.grad_accum / rows.grad_count.clamp_min(1)
        big = torch.exp(rows.log_scales).max(1).values > self.percent_dense * scene_extent
        hot = grads >= self.grad_threshold
        room = max_gaussians - len(rows)
        clone, split = hot & ~big, hot & big
        if int(clone.sum()) + int(split.sum()) > room:  # keep the strongest candidates under the cap
            order = torch.argsort(torch.where(hot, grads, torch.full_like(grads, -1.0)), descending=True)
            allowed = torch.zeros_like(hot)
            allowed[order[: max(room, 0)]] = True
            clone, split = clone & allowed, split & allowed
        clones, children = _take(rows, clone), _split_rows(rows, split)
        new = {k: torch.cat([clones[k], children[k]]) for k in clones}
        rows.add(new, optimizer)
        drop = torch.sigmoid(rows.opacities).squeeze(1) < self.min_opacity
        drop[: split.shape[0]] |= split  # split parents are replaced by their two children
        if prune_big:
            drop |= rows.max_radii > self.max_screen_radius
            drop |= torch.exp(rows.log_scales).max(1).values > 0.1 * scene_extent
        rows.keep(~drop, optimizer)
        rows.grad_accum.zero_(), rows.grad_count.zero_(), rows.max_radii.zero_()
        return {"cloned": int(clone.sum()), "split": int(split.sum()), "pruned": int(drop.sum())}


def _take(rows: PrimitiveRows, mask: torch.Tensor) -> dict[str, torch.Tensor]:
    """Copies of the parameters and source-keyframe tags of the masked rows (statistics start at 0)."""
    out = {k: v.detach()[mask] for k, v in rows.parameters_by_name().items()}
    out["kf_tag"] = rows.kf_tag[mask]
    return out


def _split_rows(rows: PrimitiveRows, mask: torch.Tensor, n: int = 2) -> dict[str, torch.Tensor]:
    """n children per masked Gaussian: means drawn from the parent, scales / (0.8 n)."""
    out = {k: v.repeat(n, *([1] * (v.dim() - 1))) for k, v in _take(rows, mask).items()}
    scales = torch.exp(out["log_scales"])
    offsets = torch.randn_like(scales) * scales
    out["means"] = out["means"] + (quat_to_rotmat(out["quats"]) @ offsets.unsqueeze(-1)).squeeze(-1)
    out["log_scales"] = torch.log(scales / (0.8 * n))
    return out
