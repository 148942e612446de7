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
from segs.modules.afme import AppearanceEncoder
from segs.modules.anchors import AnchorField
from segs.modules.config import SegsConfig
from segs.modules.decoder_average import DecoderAverage
from segs.modules.export import rgb_to_sh_dc, write_gaussian_ply
from segs.modules.fpr import fpr_loss
from segs.modules.geometry import apply_similarity, split_similarity
from segs.modules.optim import LrSchedule
from segs.modules.scene_model import Decoded, SceneModel, View
from segs.modules.sepm import initial_log_scales, voxelize


class SegsModel(SceneModel):
    """SEGS-SLAM's photorealistic map (see the module docstring for the parts)."""

    decodes_per_view = True  # Scaffold-GS decoding (anchors.py): the PLY is fitted (modules/bake.py)
    LEGACY_STATE_KEYS = {"field.params.params.": "field.rows.", "field.xyz": "field.rows.xyz", "densifier.": "field.rows.",
                         "kf_tags": "field.rows.kf_tag"}  # fmt: skip

    def __init__(self, cfg: SegsConfig):
        super().__init__()
        self.fpr, self.loss_w, self.growth, self.lr = cfg.fpr, cfg.loss, cfg.densify, cfg.lr
        self.scale = cfg.total_steps / cfg.reference_steps
        self.total_steps, self.voxel_size, self.min_new_points = cfg.total_steps, cfg.voxel_size, cfg.min_new_points
        app = cfg.appearance
        a_dim = 0 if app.kind == "none" else app.dim
        self.field = AnchorField(cfg.k, cfg.feature_dim, cfg.hidden, a_dim, cfg.use_distance, cfg.frustum_margin)
        self.appearance = AppearanceEncoder(app.kind, app.dim, app.hidden, app.max_views)
        # renders outside training decode with these weights averaged over the latest steps (0: off)
        self.decoder_average = DecoderAverage(self.decoders(), cfg.decoder_average) if cfg.decoder_average > 0 else None
        self.max_anchors = cfg.max_anchors
        if cfg.budget_mb is not None:
            self.max_anchors = min(cfg.max_anchors, self.anchors_for_budget(cfg.budget_mb))
        self._pending: list[tuple[torch.Tensor, torch.Tensor]] = []
        self.last_rendered = 0

    def anchors_for_budget(self, budget_mb: float) -> int:
        """Largest anchor count whose model (anchors + decoders + embedding) fits in budget_mb."""
        fixed = self.parameter_count() - len(self.field) * self.floats_per_anchor()
        n = int((budget_mb * 1e6 / 4 - fixed) // self.floats_per_anchor())
        if n < 1:
            raise ConfigError(f"model.budget_mb={budget_mb} is smaller than the decoders alone ({fixed * 4 / 1e6:.3f} MB)")
        return n

    def parameter_count(self) -> int:
        """Floats of the map's parameters (the decoder average's copies, a second set of the
        decoders' weights that renders use instead of the first, not counted)."""
        average = set(map(id, self.decoder_average.parameters())) if self.decoder_average is not None else set()
        return sum(p.numel() for p in self.parameters() if id(p) not in average)

    def decoders(self) -> dict[str, torch.nn.Module]:
        """The modules the decoder average follows: the three decoders and AfME's encoder."""
        out = dict(self.field.decoders())
        if (encoder := self.appearance.weights()) is not None:
            out["appearance"] = encoder
        return out

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

    def checkpoint_state(self) -> dict[str, torch.Tensor]:
        """The SLAM points waiting for min_new_points (xyz [P,3], creating kf ids [P])."""
        if not self._pending:
            return {}
        return {"pending_xyz": torch.cat([p for p, _ in self._pending]), "pending_kf": torch.cat([t for _, t in self._pending])}

    def load_checkpoint_state(self, state: dict[str, torch.Tensor]) -> None:
        xyz = state.get("pending_xyz")
        self._pending = [] if xyz is None else [(xyz.to(self.field.xyz), state["pending_kf"].to(torch.int64))]

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
        groups = self.field.rows.groups({"features": lr.features, "offsets": lr.offsets * self.scene_extent, "log_scales": lr.scales})
        for name, params in self.field.decoder_groups().items():
            groups.append({"name": name, "params": params, "lr": getattr(lr, name)})
        app = list(self.appearance.parameters())
        if app:
            groups.append({"name": "appearance", "params": app, "lr": lr.appearance})
        return groups

    def lr_schedules(self) -> dict[str, LrSchedule]:
        lr, n = self.lr, self.total_steps
        out = {"anchor.offsets": LrSchedule(lr.offsets * self.scene_extent, lr.offsets_final * self.scene_extent, n)}
        for name in ("mlp_opacity", "mlp_cov", "mlp_color", "appearance"):
            out[name] = LrSchedule(getattr(lr, name), getattr(lr, f"{name}_final"), n)
        return out

    def _on_device(self, view: View) -> View:
        """The view with its pose on the model's device (evaluation and export pass CPU poses)."""
        dev = self.field.xyz.device
        return view if view.w2c.device == dev else View(view.w2c.to(dev), view.camera, view.kf_id)

    def decode(self, view: View, step: int, averaged: bool = False) -> Decoded:
        """The anchors in the view's frustum decoded; averaged: with the decoder average's weights."""
        decoded, info = self._decode_field(view, averaged, cull=True)
        decoded.aux["info"] = info
        self.last_rendered = len(decoded)
        return decoded

    def _decode_field(self, view: View, averaged: bool, cull: bool):
        """(Decoded, DecodeInfo) of the anchor field for the view (on the model's device), with the
        decoder average's weights where `averaged` and the model keeps one, else the live ones."""
        view = self._on_device(view)
        self.appearance.scene_extent = self.scene_extent
        mlps = dict(self.decoder_average.averaged.items()) if averaged and self.decoder_average is not None else None
        embedding = self.appearance(view.w2c, view.kf_id, None if mlps is None else mlps.get("appearance"))
        return self.field.decode(view, embedding, cull=cull, decoders=mlps)

    def after_step(self) -> None:
        if self.decoder_average is not None:
            self.decoder_average.update(self.decoders())

    def compile_step_code(self) -> None:
        """The photometric loss (SceneModel) and the anchors' decoding (AnchorField.compile_decoding)."""
        super().compile_step_code()
        self.field.compile_decoding()

    def fpr_active(self, step: int) -> bool:
        f = self.fpr
        return f.enabled and self._at(f.from_step) < step < self._at(f.until_step)

    def loss(self, render, gt, decoded, step, gt_depth=None) -> dict:
        w, f = self.loss_w, self.fpr
        terms = self.photometric(render.image, gt, w.lambda_dssim)
        terms["volume"] = losses.volume(decoded.scales)
        total = terms["photometric"] + w.lambda_vol * terms["volume"]
        if self.fpr_active(step) and f.weight > 0:
            terms["fpr"] = fpr_loss(render.image, gt, f.scales, f.mode, f.hp_ratio, f.lp_ratio)
            total = total + f.weight * terms["fpr"]
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
        if self.run_steps is not None and step > self.run_steps - interval:
            return {}  # the run ends before the anchors of this round could be trained: no round in its last interval
        return self.growth.adjust(self.field, optimizer, interval, self.voxel_size, self.max_anchors)

    # -- bookkeeping ----------------------------------------------------------------------------
    @torch.no_grad()
    def count_active(self, view: View, threshold: float = 0.005) -> int:
        """Gaussians decoded for this view with opacity above threshold."""
        return int((self.decode(view, self.total_steps, averaged=True).opacities > threshold).sum())

    def counts(self) -> dict[str, float]:
        n_params = self.parameter_count()
        return {"anchors": len(self.field), "gaussians": len(self.field) * self.field.k, "rendered": self.last_rendered,
                "params": n_params, "mb": (n_params + self.field.xyz.numel()) * 4 / 1e6}  # fmt: skip

    def upgrade_state(self, state: dict, prefix: str) -> dict:
        """A checkpoint's state_dict (keys `prefix` + this model's names) made to fit this model's
        decoder average: written without one (before it existed, or with it off), the average
        starts as the checkpoint's live weights; written with one this model does not keep, it is
        dropped."""
        key = prefix + "decoder_average."
        if self.decoder_average is None:
            return {k: v for k, v in state.items() if not k.startswith(key)}
        names = {id(m): name for name, m in self.named_modules()}
        sources = {name: f"{prefix}{names[id(m)]}." for name, m in self.decoders().items()}
        return self.decoder_average.filled_state(state, key, sources)

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
    def decode_all(self, view: View) -> Decoded:
        """Every anchor decoded (no frustum culling) with this view's direction and appearance."""
        return self._decode_field(view, averaged=True, cull=False)[0]

    def export_ply(self, path: str | Path, view: View) -> int:
        """The Gaussians of decode_all as degree-0 SH (their colours are decoded, not SH)."""
        d = self.decode_all(view)
        return write_gaussian_ply(path, d.means, d.quats, d.scales, d.opacities, rgb_to_sh_dc(d.colors))
