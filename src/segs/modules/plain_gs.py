"""Plain 3D-GS (Kerbl et al. 2023): the baseline and the paper's "w/o FPR, AfME, SEPM" row.

Gaussians are initialised from the SLAM points, then grown by adaptive densification (clone
small / split large Gaussians with a large screen-space gradient) and pruned by opacity.
"""
from __future__ import annotations

import math
from pathlib import Path

import torch
import torch.nn.functional as F

from segs.modules import losses
from segs.modules.config import PlainConfig
from segs.modules.export import rgb_to_sh_dc, write_gaussian_ply
from segs.modules.geometry import apply_similarity, knn_mean_sq_dist, quat_multiply, rotmat_to_quat, split_similarity
from segs.modules.optim import LrSchedule
from segs.modules.rows import FLOAT, INDEX, PrimitiveRows
from segs.modules.scene_model import Decoded, SceneModel, View
from segs.modules.sh import eval_sh


def _logit(p: float) -> float:
    return math.log(p / (1.0 - p))


class PlainGaussians(SceneModel):
    """Unstructured 3D Gaussians with SH colours.

    Rows per Gaussian (one PrimitiveRows store `gs`): parameters means [3], log_scales [3],
    quats [4] (wxyz, unnormalised), opacity logits [1], sh_dc [1,3], sh_rest [(D+1)^2-1,3];
    buffers kf_tag (creating keyframe) and the statistics grad_accum, grad_count, max_radii.
    """

    LEGACY_STATE_KEYS = {"gs.params.": "gs.", "kf_tags": "gs.kf_tag", "grad_accum": "gs.grad_accum",
                         "grad_count": "gs.grad_count", "max_radii": "gs.max_radii"}  # fmt: skip

    def __init__(self, cfg: PlainConfig):
        super().__init__()
        self.sh_degree, self.sh_increase_every = cfg.sh_degree, cfg.sh_increase_every
        self.lambda_dssim, self.lambda_depth = cfg.lambda_dssim, cfg.lambda_depth
        self.uses_depth = cfg.lambda_depth > 0
        self.init_opacity, self.max_gaussians = cfg.init_opacity, cfg.max_gaussians
        if cfg.budget_mb is not None:
            floats = 3 + 3 + 4 + 1 + 3 * (cfg.sh_degree + 1) ** 2  # means, scales, quats, opacity, SH
            self.max_gaussians = min(cfg.max_gaussians, max(int(cfg.budget_mb * 1e6 / 4 // floats), 1))
        self.lr, self.densify, self.total_steps = cfg.lr, cfg.densify, cfg.total_steps
        self.scale = cfg.total_steps / cfg.reference_steps
        k_rest = (cfg.sh_degree + 1) ** 2 - 1
        self.gs = PrimitiveRows(
            params={"means": (3,), "log_scales": (3,), "quats": (4,), "opacities": (1,), "sh_dc": (1, 3), "sh_rest": (k_rest, 3)},
            buffers={"kf_tag": ((), INDEX), "grad_accum": ((), FLOAT), "grad_count": ((), FLOAT), "max_radii": ((), FLOAT)},
            prefix="gs.",
        )

    # -- bridge ---------------------------------------------------------------------------------
    def add_points(self, xyz, rgb, kf_ids, optimizer) -> int:
        if xyz.shape[0] == 0:
            return 0
        room = self.max_gaussians - len(self.gs)
        like = self.gs["means"]  # new rows take the parameters' dtype and device
        xyz, rgb, kf_ids = xyz[:room].to(like), rgb[:room].to(like), kf_ids[:room]
        m = xyz.shape[0]
        if m == 0:
            return 0
        d2 = knn_mean_sq_dist(xyz, torch.cat([self.gs["means"].detach(), xyz]), k=3)
        rows = {
            "means": xyz,
            "log_scales": torch.log(torch.sqrt(d2)).unsqueeze(1).repeat(1, 3),
            "quats": xyz.new_tensor([1.0, 0, 0, 0]).repeat(m, 1),
            "opacities": xyz.new_full((m, 1), _logit(self.init_opacity)),
            "sh_dc": rgb_to_sh_dc(rgb).unsqueeze(1),
            "sh_rest": xyz.new_zeros(m, self.gs.param_shapes["sh_rest"][0], 3),
            "kf_tag": kf_ids,
        }
        return self.gs.add(rows, optimizer)

    def correct_map(self, transforms, optimizer) -> int:
        moved = 0
        for kf_id, T in transforms.items():
            mask = self.gs.kf_tag == int(kf_id)
            if not bool(mask.any()):
                continue
            T = T.to(self.gs["means"])
            R, _, s = split_similarity(T)
            qR = rotmat_to_quat(R)
            with torch.no_grad():
                self.gs["means"][mask] = apply_similarity(T, self.gs["means"][mask])
                self.gs["quats"][mask] = quat_multiply(qR.expand(int(mask.sum()), 4), self.gs["quats"][mask])
                self.gs["log_scales"][mask] += math.log(s)
            moved += int(mask.sum())
        return moved

    # -- optimisation ---------------------------------------------------------------------------
    def param_groups(self) -> list[dict]:
        lr = self.lr
        lrs = {"means": lr.means * self.scene_extent, "log_scales": lr.scales, "quats": lr.quats, "opacities": lr.opacities,
               "sh_dc": lr.sh_dc, "sh_rest": lr.sh_rest}  # fmt: skip
        return self.gs.groups(lrs)

    def lr_schedules(self) -> dict[str, LrSchedule]:
        lr = self.lr
        return {"gs.means": LrSchedule(lr.means * self.scene_extent, lr.means_final * self.scene_extent, self.total_steps)}

    def _at(self, step_ref: float) -> int:
        """A reference-run (30k) iteration number in this run's steps."""
        return max(int(round(step_ref * self.scale)), 1)

    def active_sh_degree(self, step: int) -> int:
        return min(self.sh_degree, step // self._at(self.sh_increase_every))

    def decode(self, view: View, step: int, averaged: bool = False) -> Decoded:
        """The Gaussians themselves, coloured by their SH (no average is kept: `averaged` is moot)."""
        means = self.gs["means"]
        dirs = F.normalize(means - view.center.to(means), dim=-1)
        sh = torch.cat([self.gs["sh_dc"], self.gs["sh_rest"]], 1)
        return Decoded(
            means=means,
            quats=F.normalize(self.gs["quats"], dim=-1),
            scales=torch.exp(self.gs["log_scales"]),
            opacities=torch.sigmoid(self.gs["opacities"]).squeeze(1),
            colors=eval_sh(self.active_sh_degree(step), sh, dirs),
        )

    def loss(self, render, gt, decoded, step, gt_depth=None) -> dict:
        terms = self.photometric(render.image, gt, self.lambda_dssim)
        total = terms["photometric"]
        if self.lambda_depth > 0 and gt_depth is not None:
            terms["depth"] = losses.depth_l1(render.depth, gt_depth)
            total = total + self.lambda_depth * terms["depth"]
        terms["total"] = total
        return terms

    def after_backward(self, decoded, render, step) -> None:
        h, w = render.image.shape[:2]
        self.densify.record(self.gs, render.means2d.grad, render.radii, w, h)

    # -- densification --------------------------------------------------------------------------
    def maintain(self, step, optimizer) -> dict[str, float]:
        d = self.densify
        start, until = self._at(d.from_step), self._at(d.until_step)
        # 0 disables the opacity reset (and the screen-size pruning that follows the first one)
        reset = self._at(d.opacity_reset_interval) if d.opacity_reset_interval > 0 else 0
        # as SEGS's growth: densify every `interval` steps (statistics of ~100 views) unless scaled
        interval = self._at(d.interval) if d.scale_interval else int(d.interval)
        out: dict[str, float] = {}
        if start <= step < until and step % interval == 0 and len(self.gs):
            out = d.adjust(self.gs, optimizer, self.scene_extent, self.max_gaussians, prune_big=0 < reset < step)
        if reset > 0 and start <= step < until and step % reset == 0 and len(self.gs):
            capped = torch.minimum(self.gs.opacities.detach(), torch.full_like(self.gs.opacities, _logit(0.01)))
            self.gs.assign("opacities", capped, optimizer, reset_state=True)
        return out

    @torch.no_grad()
    def count_active(self, view: View, threshold: float = 0.005) -> int:
        """Gaussians with opacity above threshold (view independent for plain 3D-GS)."""
        return int((torch.sigmoid(self.gs["opacities"]) > threshold).sum())

    # -- bookkeeping ----------------------------------------------------------------------------
    def counts(self) -> dict[str, float]:
        n_params = sum(p.numel() for p in self.parameters())
        return {"anchors": 0, "gaussians": len(self.gs), "params": n_params, "mb": n_params * 4 / 1e6}

    def resize_for_state(self, state_dict) -> None:
        self.gs.resize(state_dict["gs.means"].shape[0])

    @torch.no_grad()
    def decode_all(self, view: View) -> Decoded:
        """Every Gaussian, coloured by its SH at the full degree seen from the view's centre."""
        return self.decode(view, self.total_steps)

    def export_ply(self, path: str | Path, view: View) -> int:
        """Every Gaussian with its SH coefficients (degree model.sh_degree: 3(D+1)^2-3 f_rest_*)."""
        g = self.gs
        return write_gaussian_ply(
            path, g["means"], F.normalize(g["quats"], dim=-1), torch.exp(g["log_scales"]),
            torch.sigmoid(g["opacities"]).squeeze(1), g["sh_dc"].squeeze(1), g["sh_rest"],
        )  # fmt: skip
