"""The Lightning module of photorealistic mapping: one Adam, manual optimisation, keyframe views.

Its bridge interface (called by segs.callbacks.SlamBridge, never by the SLAM code itself):
add_keyframes, update_poses, add_points, correct_map.
"""
from __future__ import annotations

import logging
import random
import time

import lightning as L
import numpy as np
import torch

from segs.modules.config import MappingConfig, RasterConfig
from segs.modules.keyframes import Keyframe, KeyframeStore
from segs.modules.metrics import psnr
from segs.modules.optim import make_adam, set_learning_rates
from segs.modules.scene_model import SceneModel, View
from segs.raster import rasterize

log = logging.getLogger(__name__)


class MappingModule(L.LightningModule):
    """Trains a SceneModel on keyframes pushed by the SLAM bridge.

    mapping.view_budget: uses per keyframe before every keyframe gets one more (reference: 2 for
    TUM/EuRoC, 8 for Replica); seed: the view sampler's.
    """

    def __init__(self, model: SceneModel, mapping: MappingConfig, raster: RasterConfig, seed: int):
        super().__init__()
        self.automatic_optimization = False
        self.model = model
        self.raster = raster
        self.store = KeyframeStore(mapping.view_budget, seed)
        self.min_scene_extent = mapping.min_scene_extent
        self.adam_eps = mapping.adam_eps
        self.iteration_ms: list[float] = []
        self.loss_history: list[float] = []

    # -- bridge interface -----------------------------------------------------------------------
    def add_keyframes(self, keyframes: list[Keyframe]) -> None:
        """New training views (image [H,W,3] uint8, w2c [4,4])."""
        for kf in keyframes:
            self.store.add(kf)
        self.model.register_views({kf.kf_id: kf.w2c for kf in keyframes})
        self._update_extent()

    def update_poses(self, poses: dict[int, torch.Tensor]) -> None:
        """Refreshed world-to-camera poses [4,4] by kf_id (unknown ids are ignored)."""
        for kf_id, w2c in poses.items():
            self.store.update_pose(int(kf_id), torch.as_tensor(w2c, dtype=torch.float32))
        self.model.register_views({k: self.store[k].w2c for k in map(int, poses) if k in self.store})
        self._update_extent()

    def add_points(self, xyz: torch.Tensor, rgb: torch.Tensor, kf_ids: torch.Tensor) -> int:
        """New SLAM map points xyz [M,3], colours [M,3] in [0,1], creating kf ids [M]."""
        return self.model.add_points(xyz.to(self.device), rgb.to(self.device), kf_ids.to(self.device), self._optimizer())

    def correct_map(self, transforms: dict[int, torch.Tensor]) -> int:
        """Loop closure: move what each kf_id created by a world-to-world similarity [4,4]."""
        return self.model.correct_map({k: torch.as_tensor(v, dtype=torch.float32) for k, v in transforms.items()}, self._optimizer())

    # -- helpers --------------------------------------------------------------------------------
    def _optimizer(self):
        try:
            return self.optimizers(use_pl_optimizer=False)
        except RuntimeError:  # not attached to a trainer / optimizer not built yet
            return None

    def _update_extent(self) -> None:
        if len(self.store) == 0:
            return
        centers = torch.stack([View(k.w2c, k.camera).center for k in self.store.frames.values()])
        radius = (centers - centers.mean(0)).norm(dim=-1).max()
        self.model.scene_extent = max(float(radius) * 1.1, self.min_scene_extent)

    def render(self, view: View, step: int | None = None):
        """Decode and rasterize one view; returns (rasterizer output, Decoded)."""
        decoded = self.model.decode(view, self.global_step if step is None else step)
        r = self.raster
        bg = torch.tensor(r.background, dtype=torch.float32, device=self.device)
        out = rasterize(
            decoded.means, decoded.quats, decoded.scales, decoded.opacities, decoded.colors,
            view.w2c.to(self.device), view.K.to(self.device), view.camera.width, view.camera.height,
            background=bg, near=r.near, far=r.far, backend=r.backend,
        )  # fmt: skip
        return out, decoded

    @torch.no_grad()
    def render_image(self, w2c: np.ndarray | torch.Tensor, camera, kf_id: int | None = None) -> dict:
        """Render at a pose (evaluation): {"image" [H,W,3], "depth" [H,W], "alpha" [H,W]} on CPU."""
        view = View(torch.as_tensor(w2c, dtype=torch.float32), camera, kf_id)
        out, _ = self.render(view)
        return {"image": out.image.clamp(0, 1).cpu(), "depth": out.depth.cpu(), "alpha": out.alpha.cpu()}

    # -- training -------------------------------------------------------------------------------
    def configure_optimizers(self):
        return make_adam(self.model.param_groups(), eps=self.adam_eps)

    def training_step(self, batch, batch_idx):
        t0 = time.perf_counter()
        opt = self.optimizers(use_pl_optimizer=False)
        step = self.global_step
        kf = self.store.sample()
        view = View(kf.w2c.to(self.device), kf.camera, kf.kf_id)
        gt = kf.rgb().to(self.device)
        out, decoded = self.render(view, step)
        depth = kf.depth.to(self.device) if kf.depth is not None else None
        terms = self.model.loss(out, gt, decoded, step, depth)
        if terms["total"].requires_grad:
            self.manual_backward(terms["total"])
            self.model.after_backward(decoded, out, step)
        set_learning_rates(opt, self.model.lr_schedules(), step)
        self.optimizers().step()
        opt.zero_grad(set_to_none=True)
        edits = self.model.maintain(step + 1, opt)
        self.iteration_ms.append((time.perf_counter() - t0) * 1000.0)
        self.loss_history.append(float(terms["total"].detach()))
        self._log_step(terms, out.image.detach(), gt, edits)
        return terms["total"].detach()

    def _log_step(self, terms: dict, image: torch.Tensor, gt: torch.Tensor, edits: dict) -> None:
        counts = self.model.counts()
        self.log("loss", terms["total"].detach(), prog_bar=True, on_step=True, on_epoch=False)
        self.log("gaussians", float(counts["gaussians"]), prog_bar=True, on_step=True, on_epoch=False)
        metrics = {f"train/{k}": v.detach() for k, v in terms.items() if k != "total" and torch.is_tensor(v)}
        metrics["train/psnr"] = psnr(image, gt)
        metrics["train/iteration_ms"] = self.iteration_ms[-1]
        metrics["model/anchors"] = float(counts["anchors"])
        metrics["model/keyframes"] = float(len(self.store))
        metrics.update({f"densify/{k}": float(v) for k, v in edits.items()})
        self.log_dict(metrics, on_step=True, on_epoch=False)

    # -- checkpoints ----------------------------------------------------------------------------
    def on_save_checkpoint(self, checkpoint: dict) -> None:
        checkpoint["segs"] = {
            "store": self.store.state_dict(),
            "scene_extent": self.model.scene_extent,
            "rng": {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()},
        }

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        sd = {k.removeprefix("model."): v for k, v in checkpoint["state_dict"].items() if k.startswith("model.")}
        self.model.resize_for_state(sd)
        extra = checkpoint.get("segs", {})
        if "store" in extra:
            self.store.load_state_dict(extra["store"])
        self.model.scene_extent = extra.get("scene_extent", self.model.scene_extent)
        if "rng" in extra:
            torch.set_rng_state(extra["rng"]["torch"])
            np.random.set_state(extra["rng"]["numpy"])
            random.setstate(extra["rng"]["python"])
