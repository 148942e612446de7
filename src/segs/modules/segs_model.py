"""The SEGS scene model: SEPM anchors + Scaffold decoding + AfME + FPR + anchor growth.

Iteration numbers in the config are the reference implementation's for a 30,000-iteration run
(`reference_steps`); they are scaled by total_steps / reference_steps so that a shorter CPU
budget runs the same schedule compressed.
"""
from __future__ import annotations

import math
from pathlib import Path

import torch

from segs.errors import ConfigError
from segs.modules import losses
from segs.modules.afme import KINDS, AppearanceEncoder
from segs.modules.anchors import AnchorField
from segs.modules.densification import AnchorGrowth
from segs.modules.export import rgb_to_sh_dc, write_gaussian_ply
from segs.modules.fpr import MODES, fpr_loss
from segs.modules.geometry import apply_similarity, split_similarity
from segs.modules.optim import LrSchedule
from segs.modules.scene_model import Decoded, SceneModel, View
from segs.modules.sepm import initial_log_scales, voxelize

_LR_DEFAULTS = {
    "offsets": 0.01, "offsets_final": 1e-4, "features": 0.0075, "scales": 0.005,
    "mlp_opacity": 0.002, "mlp_opacity_final": 2e-5, "mlp_cov": 0.004, "mlp_cov_final": 0.004,
    "mlp_color": 0.008, "mlp_color_final": 5e-5, "appearance": 0.05, "appearance_final": 5e-4,
}  # fmt: skip


def _check(name: str, ok: bool, value, expected: str) -> None:
    if not ok:
        raise ConfigError(f"model.{name}={value!r} is out of range: expected {expected}")


class SegsModel(SceneModel):
    """SEGS-SLAM's photorealistic map (see the module docstring for the parts)."""

    def __init__(self, k: int = 10, feature_dim: int = 32, hidden: int = 32, use_distance: bool = False,
                 voxel_size: float = 0.001, min_new_points: int = 10, max_anchors: int = 200_000,
                 appearance: dict | None = None, fpr: dict | None = None, loss: dict | None = None,
                 densify: dict | None = None, lr: dict | None = None, reference_steps: int = 30000,
                 total_steps: int = 30000, frustum_margin: float = 0.15, budget_mb: float | None = None):  # fmt: skip
        super().__init__()
        app = {"kind": "linear", "dim": 32, "hidden": 32, **dict(appearance or {})}
        self.fpr = {"enabled": True, "scales": 3, "mode": "high", "hp_ratio": 0.4, "lp_ratio": 0.1, "from_step": 5000, "until_step": 15000, **dict(fpr or {})}
        self.loss_w = {"lambda_dssim": 0.2, "lambda_vol": 0.01, "lambda_hf": 0.01, **dict(loss or {})}
        self.dcfg = {"stats_from": 500, "grow_from": 1500, "until": 25000, "interval": 100, "scale_interval": False,
                     "grad_threshold": 2e-4, "update_depth": 3, "init_factor": 16, "hierarchy_factor": 4, "min_opacity": 0.005,
                     "success_threshold": 0.8, **dict(densify or {})}  # fmt: skip
        self.lr = {**_LR_DEFAULTS, **dict(lr or {})}
        self._validate(k, feature_dim, hidden, voxel_size, max_anchors, app, reference_steps, total_steps)
        self.scale = total_steps / reference_steps
        self.total_steps, self.voxel_size, self.min_new_points = total_steps, voxel_size, min_new_points
        a_dim = 0 if app["kind"] == "none" else int(app["dim"])
        self.field = AnchorField(k, feature_dim, hidden, a_dim, use_distance, frustum_margin)
        self.appearance = AppearanceEncoder(app["kind"], int(app["dim"]), int(app["hidden"]), int(app.get("max_views", 4096)))
        self.growth = AnchorGrowth(**self.dcfg)
        self.max_anchors = max_anchors
        if budget_mb is not None:
            _check("budget_mb", budget_mb > 0, budget_mb, "> 0 (MB) or null")
            self.max_anchors = min(max_anchors, self.anchors_for_budget(budget_mb))
        self._pending: list[tuple[torch.Tensor, torch.Tensor]] = []
        self.last_rendered = 0

    def _validate(self, k, feature_dim, hidden, voxel_size, max_anchors, app, reference_steps, total_steps) -> None:
        _check("k", isinstance(k, int) and k > 0, k, "an integer > 0")
        _check("feature_dim", feature_dim > 0, feature_dim, "> 0")
        _check("hidden", hidden > 0, hidden, "> 0")
        _check("voxel_size", voxel_size > 0, voxel_size, "> 0 (metres)")
        _check("max_anchors", max_anchors > 0, max_anchors, "> 0")
        _check("appearance.kind", app["kind"] in KINDS, app["kind"], f"one of {KINDS}")
        _check("appearance.dim", app["kind"] == "none" or int(app["dim"]) > 0, app["dim"], "> 0")
        _check("fpr.mode", self.fpr["mode"] in MODES, self.fpr["mode"], f"one of {MODES}")
        _check("fpr.scales", int(self.fpr["scales"]) >= 1, self.fpr["scales"], ">= 1")
        _check("densify.interval", self.dcfg["interval"] > 0, self.dcfg["interval"], "> 0")
        _check("reference_steps", reference_steps > 0 and total_steps > 0, reference_steps, "> 0")
        for name, v in self.lr.items():
            _check(f"lr.{name}", v >= 0, v, ">= 0")
        for name, v in self.loss_w.items():
            _check(f"loss.{name}", v >= 0, v, ">= 0")

    def anchors_for_budget(self, budget_mb: float) -> int:
        """Largest anchor count whose model (anchors + decoders + embedding) fits in budget_mb."""
        fixed = sum(p.numel() for p in self.parameters()) - len(self.field) * self.floats_per_anchor()
        n = int((budget_mb * 1e6 / 4 - fixed) // self.floats_per_anchor())
        if n < 1:
            raise ConfigError(f"model.budget_mb={budget_mb} is smaller than the decoders alone ({fixed * 4 / 1e6:.3f} MB)")
        return n

    def floats_per_anchor(self) -> int:
        """Stored floats per anchor: position, feature, k offsets, 6 log-scales."""
        return 3 + self.field.feature_dim + 3 * self.field.k + 6

    def _interval(self) -> int:
        """Steps between grow / prune rounds: the reference's 100 views of statistics, or scaled."""
        if self.growth.scale_interval:
            return max(self._at(self.growth.interval), 1)
        return int(self.growth.interval)

    def _at(self, step_ref: float) -> int:
        """A reference-run iteration number in this run's steps."""
        return int(round(step_ref * self.scale))

    # -- bridge ---------------------------------------------------------------------------------
    def add_points(self, xyz, rgb, kf_ids, optimizer) -> int:
        """SEPM: voxelize new points, drop voxels that hold an anchor, append the rest."""
        if xyz.shape[0]:
            self._pending.append((xyz.to(self.field.xyz), kf_ids.to(torch.int64)))
        if sum(p.shape[0] for p, _ in self._pending) < self.min_new_points and len(self.field):
            return 0
        pts = torch.cat([p for p, _ in self._pending]) if self._pending else xyz.new_zeros((0, 3))
        tags = torch.cat([t for _, t in self._pending]) if self._pending else kf_ids.new_zeros(0)
        self._pending = []
        centres, cell = voxelize(pts, self.voxel_size, existing=self.field.xyz)
        m = min(centres.shape[0], max(self.max_anchors - len(self.field), 0))  # anchor cap
        if m == 0:
            return 0
        centres, ok = centres[:m], (cell >= 0) & (cell < m)
        new_tags = torch.zeros(m, dtype=torch.int64, device=pts.device).scatter_(0, cell[ok], tags[ok])
        feats = pts.new_zeros(m, self.field.feature_dim)
        return self.field.add(centres, feats, initial_log_scales(centres, self.field.xyz), new_tags, optimizer)

    def correct_map(self, transforms, optimizer) -> int:
        """Move the anchors created from each corrected keyframe's points (positions, scales, offsets)."""
        moved = 0
        for kf_id, T in transforms.items():
            mask = self.field.rows.kf_tag == int(kf_id)
            if not bool(mask.any()):
                continue
            T = T.to(self.field.xyz)
            R, _, s = split_similarity(T)
            with torch.no_grad():
                self.field.xyz[mask] = apply_similarity(T, self.field.xyz[mask])
                ls = self.field.rows.log_scales
                old = torch.exp(ls[mask][:, :3])
                ls[mask] += math.log(s)
                off = self.field.rows.offsets
                world = off[mask] * old[:, None, :]  # [M,k,3] offset vectors in world units
                off[mask] = (s * world @ R.T) / (old[:, None, :] * s)
            moved += int(mask.sum())
        return moved

    def register_views(self, views: dict[int, torch.Tensor]) -> None:
        for kf_id, w2c in views.items():
            self.appearance.register_view(int(kf_id), View(w2c, None).center)

    # -- optimisation ---------------------------------------------------------------------------
    def param_groups(self) -> list[dict]:
        lr = self.lr
        groups = self.field.rows.groups(
            {"features": lr["features"], "offsets": lr["offsets"] * self.scene_extent, "log_scales": lr["scales"]}
        )
        for name, params in self.field.decoder_groups().items():
            groups.append({"name": name, "params": params, "lr": lr[name]})
        app = list(self.appearance.parameters())
        if app:
            groups.append({"name": "appearance", "params": app, "lr": lr["appearance"]})
        return groups

    def lr_schedules(self) -> dict[str, LrSchedule]:
        lr, n = self.lr, self.total_steps
        out = {"anchor.offsets": LrSchedule(lr["offsets"] * self.scene_extent, lr["offsets_final"] * self.scene_extent, n)}
        for name in ("mlp_opacity", "mlp_cov", "mlp_color", "appearance"):
            out[name] = LrSchedule(lr[name], lr[f"{name}_final"], n)
        return out

    def _on_device(self, view: View) -> View:
        """The view with its pose on the model's device (evaluation and export pass CPU poses)."""
        dev = self.field.xyz.device
        return view if view.w2c.device == dev else View(view.w2c.to(dev), view.camera, view.kf_id)

    def decode(self, view: View, step: int) -> Decoded:
        view = self._on_device(view)
        self.appearance.scene_extent = self.scene_extent
        embedding = self.appearance(view.w2c, view.kf_id)
        decoded, info = self.field.decode(view, embedding)
        decoded.aux["info"] = info
        self.last_rendered = len(decoded)
        return decoded

    def fpr_active(self, step: int) -> bool:
        f = self.fpr
        return bool(f["enabled"]) and self._at(f["from_step"]) < step < self._at(f["until_step"])

    def loss(self, render, gt, decoded, step, gt_depth=None) -> dict:
        w = self.loss_w
        terms = losses.photometric(render.image, gt, w["lambda_dssim"])
        terms["volume"] = losses.volume(decoded.scales)
        total = terms["photometric"] + w["lambda_vol"] * terms["volume"]
        if self.fpr_active(step) and w["lambda_hf"] > 0:
            f = self.fpr
            terms["fpr"] = fpr_loss(render.image, gt, int(f["scales"]), f["mode"], f["hp_ratio"], f["lp_ratio"])
            total = total + w["lambda_hf"] * terms["fpr"]
        terms["total"] = total
        return terms

    def after_backward(self, decoded, render, step) -> None:
        if self._at(self.growth.stats_from) <= step < self._at(self.growth.until):
            h, w = render.image.shape[:2]
            self.growth.record(self.field, decoded.aux["info"], render.means2d.grad, render.radii, w, h)

    def maintain(self, step, optimizer) -> dict[str, float]:
        interval = self._interval()
        if not (self._at(self.growth.grow_from) < step < self._at(self.growth.until)) or step % interval:
            return {}
        return self.growth.adjust(self.field, optimizer, interval, self.voxel_size, self.max_anchors)

    # -- bookkeeping ----------------------------------------------------------------------------
    @torch.no_grad()
    def count_active(self, view: View, threshold: float = 0.005) -> int:
        """Gaussians decoded for this view with opacity above threshold."""
        return int((self.decode(view, self.total_steps).opacities > threshold).sum())

    def counts(self) -> dict[str, float]:
        n_params = sum(p.numel() for p in self.parameters())
        return {"anchors": len(self.field), "gaussians": len(self.field) * self.field.k, "rendered": self.last_rendered,
                "params": n_params, "mb": (n_params + self.field.xyz.numel()) * 4 / 1e6}  # fmt: skip

    def resize_for_state(self, state_dict) -> None:
        self.field.rows.resize(state_dict["field.rows.features"].shape[0])
        if "appearance.centers" in state_dict:
            self.appearance.centers = torch.zeros_like(state_dict["appearance.centers"])
            self.appearance.center_ids = torch.zeros_like(state_dict["appearance.center_ids"])

    def get_extra_state(self) -> dict:
        return {"appearance": self.appearance.extra_state()}

    def set_extra_state(self, state: dict) -> None:
        if self.appearance.kind == "ae":
            self.appearance.view_rows = {int(k): int(v) for k, v in state["appearance"]["view_rows"].items()}

    @torch.no_grad()
    def export_ply(self, path: str | Path, view: View) -> int:
        """Decode every anchor (no frustum culling) with this view's direction and appearance."""
        view = self._on_device(view)
        embedding = self.appearance(view.w2c, view.kf_id)
        d, _ = self.field.decode(view, embedding, cull=False)
        return write_gaussian_ply(path, d.means, d.quats, d.scales, d.opacities, rgb_to_sh_dc(d.colors))
