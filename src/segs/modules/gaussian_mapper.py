"""The Gaussian mapper: the Lightning module that trains the photorealistic map (one Adam,
manual optimisation) on the training views pushed by the SLAM bridge.

It implements segs.modules.contract.GaussianMapper, the only part of it the bridge, the
evaluation and the callbacks use: add_keyframes, update_poses, add_points, correct_map, counts,
first_view, render_image, count_active, training_views, gaussians, export_ply.
"""
from __future__ import annotations

import dataclasses
import importlib.util
import logging
import math
import os
import random
import shutil
import time

import lightning as L
import numpy as np
import torch

from segs.errors import ConfigError
from segs.modules.bake import refine_cloud
from segs.modules.config import MappingConfig, RasterConfig
from segs.modules.contract import GaussianCloud, MapCounts, TrainingView
from segs.modules.export import rgb_to_sh_dc, write_gaussian_ply
from segs.modules.metrics import psnr_tensor
from segs.modules.optim import make_adam, set_learning_rates
from segs.modules.resolution import coarse_camera, coarse_depth, coarse_image, downscale_factor
from segs.modules.scene_model import SceneModel, View, upgrade_state_keys
from segs.modules.training_views import TrainingViews
from segs.raster import EPS2D, rasterize

log = logging.getLogger(__name__)


LOSS_READ = 100  # training losses are read back to the host in batches, and the rendered Gaussians checked
# for non-finite values on one step in LOSS_READ: on a GPU each read is a sync


def compile_unavailable(device: torch.device) -> str | None:
    """Why torch.compile cannot build code for `device`, or None: a CUDA device needs Triton and
    compute capability 7.0 or newer, the CPU a C++ compiler."""
    if device.type == "cuda":
        if importlib.util.find_spec("triton") is None:
            return "Triton is not installed (torch.compile's CUDA code generator)"
        major, minor = torch.cuda.get_device_capability(device)
        return None if major >= 7 else f"compute capability {major}.{minor} is below Triton's 7.0"
    if device.type == "cpu":
        compilers = [os.environ.get("CXX"), "g++", "clang++", "c++"]
        return None if any(c and shutil.which(c) for c in compilers) else "no C++ compiler (g++, clang++ or $CXX) on the PATH"
    return f"no compiled step code for {device.type} devices"


class GaussianMapperModule(L.LightningModule):
    """Trains a SceneModel (SEGS anchors or plain 3D-GS) on the training views of the bridge.

    mapping.view_budget: uses per keyframe before every keyframe gets one more (reference: 2 for
    TUM/EuRoC, 8 for Replica); mapping.num_downscales / downscale_phase: the coarse-to-fine
    resolution schedule (segs.modules.resolution); seed: the view sampler's.
    """

    def __init__(self, model: SceneModel, mapping: MappingConfig, raster: RasterConfig, seed: int):
        super().__init__()
        self.automatic_optimization = False
        self.model = model
        self.raster = raster
        self.views = TrainingViews(mapping.view_budget, seed)
        self.min_scene_extent = mapping.min_scene_extent
        self.adam_eps = mapping.adam_eps
        self.num_downscales, self.downscale_phase = mapping.num_downscales, mapping.downscale_phase
        self.render_filter = mapping.render_filter
        self.trained_factor = 1  # the image size divisor of the latest training step
        # its pixel area (factor^2) averaged over the latest steps, mapping.render_filter_decay per
        # step (render_image's filter; None before the first step: trained_factor's)
        self.trained_area: float | None = None
        self.render_filter_decay = mapping.render_filter_decay
        self.compile_mode = mapping.compile  # None: on a CUDA device (on_fit_start)
        self.compiled = False
        self.iteration_ms: list[float] = []
        self.progress_values: dict[str, float] = {}  # the progress bar's figures (StepProgressBar), set on written steps
        self._losses: list[float] = []
        self._pending_losses: list[torch.Tensor] = []  # on the device, read back every LOSS_READ steps
        # per kf_id: (the host pose object it was made from, the view on the training device)
        self._device_views: dict[int, tuple[torch.Tensor, TrainingView]] = {}
        self._device_K: dict = {}  # (Camera, device) -> K [3,3] on the training device
        self.register_buffer("background", torch.tensor(raster.background, dtype=torch.float32), persistent=False)
        self.raster_backend: str | None = None  # the backend that rendered last (provenance)
        self.restored_step = 0  # the loaded checkpoint's step: renders outside a trainer (segs.view) use it

    # -- the bridge contract (segs.modules.contract.GaussianMapper) -----------------------------
    @property
    def uses_depth(self) -> bool:
        """Whether the scene model's loss reads the keyframes' depth."""
        return self.model.uses_depth

    def add_keyframes(self, views: list[TrainingView]) -> None:
        """New training views (image [H,W,3] uint8, w2c [4,4] float32); their depth is kept only
        when the model's loss reads it."""
        for view in views:
            self.views.add(view if self.uses_depth or view.depth is None else dataclasses.replace(view, depth=None))
        self.model.register_views({v.kf_id: v.w2c for v in views})
        self._update_extent()

    def update_poses(self, poses: dict[int, torch.Tensor]) -> None:
        """Refreshed world-to-camera poses [4,4] float32 by kf_id (unknown ids are ignored)."""
        known = {int(k): w2c for k, w2c in poses.items() if int(k) in self.views}
        for kf_id, w2c in known.items():
            self.views.update_pose(kf_id, w2c)
        if known:
            self.model.register_views(known)
            self._update_extent()

    def add_points(self, xyz: torch.Tensor, rgb: torch.Tensor, kf_ids: torch.Tensor) -> int:
        """New SLAM map points xyz [M,3], colours [M,3] in [0,1], creating kf ids [M]."""
        return self.model.add_points(xyz.to(self.device), rgb.to(self.device), kf_ids.to(self.device), self._optimizer())

    def correct_map(self, transforms: dict[int, torch.Tensor]) -> int:
        """Loop closure: move what each kf_id created by a world-to-world similarity [4,4]."""
        return self.model.correct_map(transforms, self._optimizer())

    def counts(self) -> MapCounts:
        c = self.model.counts()
        return MapCounts(len(self.views), int(c["anchors"]), int(c["gaussians"]), int(c["params"]), float(c["mb"]))

    def first_view(self) -> TrainingView | None:
        return self.views.first()

    @torch.no_grad()
    def count_active(self, w2c: np.ndarray | torch.Tensor, camera, threshold: float) -> int:
        """Gaussians of the view at w2c [4,4] whose opacity exceeds threshold."""
        return self.model.count_active(View(torch.as_tensor(w2c, dtype=torch.float32), camera), threshold)

    def training_views(self) -> list[TrainingView]:
        return list(self.views.frames.values())

    @torch.no_grad()
    def gaussians(self, w2c: np.ndarray | torch.Tensor | None = None, camera=None) -> GaussianCloud | None:
        """The Gaussians on the CPU. w2c [4,4] given: those a render from that camera draws (SEGS:
        the anchors in its frustum, decoded for its direction and a novel view's appearance),
        camera: its intrinsics (default: the first training view's). Without w2c: every Gaussian,
        decoded with the first training view's direction and appearance (export_ply's)."""
        first = self.views.first()
        if first is None:
            return None
        if w2c is None:
            d = self.model.decode_all(View(first.w2c, first.camera, first.kf_id))
        else:
            view = View(torch.as_tensor(w2c, dtype=torch.float32), camera or first.camera)
            d = self.model.decode(view, self.model.total_steps, averaged=True)
        cpu = lambda t: t.detach().to("cpu", torch.float32)  # noqa: E731
        return GaussianCloud(cpu(d.means), cpu(d.quats), cpu(d.scales), cpu(d.opacities), cpu(d.colors))

    def export_ply(self, path, cloud: GaussianCloud | None = None) -> int:
        """The map as a 3D-GS PLY: `cloud` (from `fitted_cloud`) when given, else the model's own
        export (decoded with the first training view's direction and appearance)."""
        if cloud is not None:
            return write_gaussian_ply(path, cloud.means, cloud.quats, cloud.scales, cloud.opacities, rgb_to_sh_dc(cloud.colors))
        first = self.views.first()
        if first is None:
            return 0
        return self.model.export_ply(path, View(first.w2c, first.camera, first.kf_id))

    def fitted_cloud(self, steps: int, progress=None) -> GaussianCloud | None:
        """For a model that decodes its Gaussians per view (SEGS): `gaussians()` fitted for `steps`
        steps to the training views as a standard 3D-GS renderer draws them (segs.modules.bake);
        None for a model whose own parameters are its export (plain 3D-GS) or before a view.
        progress(step) is called after every step."""
        if not self.model.decodes_per_view or (cloud := self.gaussians()) is None:
            return None
        render = lambda gaussians, view: self.render_cloud(gaussians, view.w2c, view.camera)  # noqa: E731
        return refine_cloud(cloud, self.training_views(), steps, render, self.model.scene_extent, self.device, progress=progress)

    def render_cloud(self, gaussians: tuple[torch.Tensor, ...], w2c: np.ndarray | torch.Tensor, camera) -> torch.Tensor:
        """[H,W,3] (not clamped, gradient kept): Gaussians (means [N,3], unit quats [N,4], scales [N,3],
        opacities [N], colours [N,3]) drawn at w2c [4,4] as a standard 3D-GS renderer draws them
        (full size, EPS2D), with this mapper's rasterizer settings."""
        view = View(torch.as_tensor(w2c, dtype=torch.float32), camera)
        r, dev = self.raster, self.device
        means, quats, scales, opacities, colors = (t.to(dev) for t in gaussians)
        out = rasterize(means, quats, scales, opacities, colors, view.w2c.to(dev), self._K(view), camera.width, camera.height,
                        background=self.background, near=r.near, far=r.far, backend=r.backend, eps2d=EPS2D)  # fmt: skip
        return out.image

    # -- helpers --------------------------------------------------------------------------------
    def _optimizer(self):
        try:
            return self.optimizers(use_pl_optimizer=False)
        except RuntimeError:  # not attached to a trainer / optimizer not built yet
            return None

    def _update_extent(self) -> None:
        if len(self.views) == 0:
            return
        centers = torch.stack([View(v.w2c, v.camera).center for v in self.views.frames.values()])
        radius = (centers - centers.mean(0)).norm(dim=-1).max()
        self.model.scene_extent = max(float(radius) * 1.1, self.min_scene_extent)

    @property
    def loss_history(self) -> list[float]:
        """The total loss of every training step of this process, in order."""
        self._read_losses()
        return self._losses

    def _read_losses(self) -> None:
        """Move the pending losses to the history; FloatingPointError at the first non-finite one
        (a NaN in the map empties it silently: its opacities fail the `> 0` test)."""
        if self._pending_losses:
            read = torch.stack(self._pending_losses).tolist()
            first = len(self._losses)
            self._losses.extend(read)
            self._pending_losses = []
            bad = next((i for i, v in enumerate(read) if not math.isfinite(v)), None)
            if bad is not None:
                raise FloatingPointError(f"training step {first + bad}: the loss is {read[bad]} (a non-finite value in "
                                         "the map, its gradients or the training view); training stopped")  # fmt: skip

    def _on_device(self, kf: TrainingView) -> TrainingView:
        """kf with its image, depth and pose on the training device, kept per keyframe (on a GPU a
        host-to-device copy inside the step waits for the device; on the CPU the entry holds the
        same tensors) and made again when the keyframe's pose is replaced (update_poses)."""
        hit = self._device_views.get(kf.kf_id)
        if hit is None or hit[0] is not kf.w2c or hit[1].image.device != self.device:
            to = lambda t: None if t is None else t.to(self.device)  # noqa: E731
            hit = self._device_views[kf.kf_id] = (kf.w2c, dataclasses.replace(kf, image=to(kf.image), w2c=to(kf.w2c), depth=to(kf.depth)))
        return hit[1]

    def _K(self, view: View) -> torch.Tensor:
        """view.K [3,3] on the training device, made once per camera."""
        key = (view.camera, self.device)
        if key not in self._device_K:
            self._device_K[key] = view.K.to(self.device)
        return self._device_K[key]

    def render(self, view: View, step: int | None = None, check_values: bool = True, eps2d: float = EPS2D,
               averaged: bool = False):  # fmt: skip
        """Decode and rasterize one view; returns (rasterizer output, Decoded). check_values:
        the rasterizer reads the Gaussians back for non-finite values (on a GPU, a wait); eps2d:
        the rasterizer's low-pass filter (pixels^2); averaged: a render outside training (the
        model's decoder average, SceneModel.decode)."""
        if step is None:
            step = self.global_step if self._trainer is not None else self.restored_step
        decoded = self.model.decode(view, step, averaged=averaged)
        r = self.raster
        out = rasterize(
            decoded.means, decoded.quats, decoded.scales, decoded.opacities, decoded.colors,
            view.w2c.to(self.device), self._K(view), view.camera.width, view.camera.height,
            background=self.background, near=r.near, far=r.far, backend=r.backend, check_values=check_values, eps2d=eps2d,
        )  # fmt: skip
        self.raster_backend = out.backend
        return out, decoded

    @torch.no_grad()
    def render_image(self, w2c: np.ndarray | torch.Tensor, camera, kf_id: int | None = None) -> dict:
        """Render at a pose (evaluation): {"image" [H,W,3], "depth" [H,W], "alpha" [H,W]} on CPU."""
        view = View(torch.as_tensor(w2c, dtype=torch.float32), camera, kf_id)
        out, _ = self.render(view, eps2d=self.render_eps2d(), averaged=True)
        return {"image": out.image.clamp(0, 1).cpu(), "depth": out.depth.cpu(), "alpha": out.alpha.cpu()}

    def render_eps2d(self) -> float:
        """The low-pass filter (pixels^2) of a full-size render (mapping.render_filter): with
        "trained", 3D-GS's filter at the pixel size the map was trained at, EPS2D * factor^2 (a map
        fitted at 1/2 size, through 0.3 px^2 of its pixels, is seen through 1.2 px^2 of full-size
        ones), factor^2 averaged over the latest steps (mapping.render_filter_decay) so that right
        after a coarse-to-fine switch the map is drawn as its Gaussians were fitted; with "fixed",
        EPS2D."""
        if self.render_filter != "trained":
            return EPS2D
        return EPS2D * (self.trained_factor**2 if self.trained_area is None else self.trained_area)

    # -- training -------------------------------------------------------------------------------
    def on_fit_start(self) -> None:
        """The model learns the run's length (SceneModel.run_steps); mapping.compile: the model's
        per-step tensor code compiled (null: on a CUDA device that torch.compile can build for,
        else eager with a note in the log; true: an error if it cannot)."""
        self.model.run_steps = self.trainer.max_steps if self.trainer.max_steps > 0 else None
        if self.compiled or self.compile_mode is False:
            return
        if self.compile_mode is None and self.device.type != "cuda":
            return
        reason = compile_unavailable(self.device)
        if reason is not None:
            if self.compile_mode:
                raise ConfigError(f"mapping.compile=true: {reason}; set mapping.compile=false")
            log.warning("mapping.compile: %s; the training step runs eager", reason)
            return
        self.model.compile_step_code()
        self.compiled = True

    def on_train_end(self) -> None:
        self._read_losses()  # the last steps' losses: a non-finite one stops the run before evaluation

    def configure_optimizers(self):
        return make_adam(self.model.param_groups(), eps=self.adam_eps)

    def training_step(self, batch, batch_idx):
        t0 = time.perf_counter()
        opt = self.optimizers(use_pl_optimizer=False)
        step = self.global_step
        kf = self._on_device(self.views.sample())  # image, depth and pose already on the device
        factor = self.trained_factor = self.resolution_factor(step)
        d = self.render_filter_decay if self.trained_area is not None else 0.0
        self.trained_area = d * self.trained_area + (1.0 - d) * factor**2 if d else float(factor**2)
        view = View(kf.w2c, coarse_camera(kf.camera, factor), kf.kf_id)
        gt = coarse_image(kf.rgb(), factor)
        out, decoded = self.render(view, step, check_values=step % LOSS_READ == 0)  # and the losses: _read_losses
        depth = coarse_depth(kf.depth, factor) if kf.depth is not None and self.uses_depth else None
        terms = self.model.loss(out, gt, decoded, step, depth)
        if terms["total"].requires_grad:
            self.manual_backward(terms["total"])
            self.model.after_backward(decoded, out, step)
        set_learning_rates(opt, self.model.lr_schedules(), step)
        self.optimizers().step()
        opt.zero_grad(set_to_none=True)
        self.model.after_step()
        edits = self.model.maintain(step + 1, opt)
        self.iteration_ms.append((time.perf_counter() - t0) * 1000.0)
        self._pending_losses.append(terms["total"].detach())
        if len(self._pending_losses) >= LOSS_READ:
            self._read_losses()
        n = self.trainer.log_every_n_steps  # Lightning's rule: 0 never writes
        if n > 0 and ((step + 1) % n == 0 or self.trainer.should_stop):
            self._log_step(step, terms, out.image.detach(), gt, edits, factor)
        return terms["total"].detach()

    def resolution_factor(self, step: int) -> int:
        """Image size divisor of training step `step` (1 = full size; coarse-to-fine schedule over
        the model's schedule, model.total_steps: trainer.max_steps or mapping.min_schedule_steps)."""
        total = self.model.total_steps if self._trainer is not None else -1
        return downscale_factor(step, total, self.num_downscales, self.downscale_phase)

    def _log_step(self, step: int, terms: dict, image: torch.Tensor, gt: torch.Tensor, edits: dict, factor: int) -> None:
        """The step's scalars, on the steps the logger writes (Lightning's rule: every
        log_every_n_steps-th optimizer step; densification runs every 100 steps, on such a step
        with the default 10): logging every step cost 3-4 ms of a 35-55 ms CPU step. The device's
        scalars are read back in one copy and written straight to the loggers at `step`, as
        Lightning would, and the progress bar's figures kept in `progress_values` (StepProgressBar):
        through `self.log` (Lightning's result collection, about 0.2 ms of Python per value) a
        written step cost 3.6 ms on the CPU (0.7 ms so) and about 8 ms on a GPU's host."""
        counts = self.model.counts()
        on_device = {"loss": terms["total"], **{f"train/{k}": v for k, v in terms.items() if k != "total" and torch.is_tensor(v)},
                     "train/psnr": psnr_tensor(image, gt)}  # fmt: skip
        read = torch.stack([v.detach().reshape(()).double() for v in on_device.values()]).cpu()
        values = dict(zip(on_device, read.tolist()))
        self.progress_values = {"loss": values["loss"], "gaussians": float(counts["gaussians"])}
        metrics = {**values, **self.progress_values, "train/iteration_ms": self.iteration_ms[-1],
                   "train/downscale": float(factor), "model/anchors": float(counts["anchors"]), "model/keyframes": float(len(self.views)),
                   **{f"densify/{k}": float(v) for k, v in edits.items()}}  # fmt: skip
        for logger in self.loggers:
            logger.log_metrics(metrics, step=step)

    # -- checkpoints ----------------------------------------------------------------------------
    def on_save_checkpoint(self, checkpoint: dict) -> None:
        checkpoint["segs"] = {
            "store": self.views.state_dict(),
            "scene_extent": self.model.scene_extent,
            "trained_factor": self.trained_factor,
            "trained_area": self.trained_area,
            "model": self.model.checkpoint_state(),  # e.g. SEGS's points waiting for min_new_points
            "rng": {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()},
        }

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        # checkpoints of the layout before the PrimitiveRows store load under the new names
        checkpoint["state_dict"] = upgrade_state_keys(checkpoint["state_dict"], self.model.LEGACY_STATE_KEYS, "model.")
        checkpoint["state_dict"] = self.model.upgrade_state(checkpoint["state_dict"], "model.")
        sd = {k.removeprefix("model."): v for k, v in checkpoint["state_dict"].items() if k.startswith("model.")}
        self.model.resize_for_state(sd)
        self.restored_step = int(checkpoint.get("global_step", 0))
        extra = checkpoint.get("segs", {})
        if "store" in extra:
            self.views.load_state_dict(extra["store"])
        self.model.scene_extent = extra.get("scene_extent", self.model.scene_extent)
        self.trained_factor = int(extra.get("trained_factor", 1))  # checkpoints before it: full size
        self.trained_area = extra.get("trained_area")  # checkpoints before it: trained_factor's area
        self.model.load_checkpoint_state(extra.get("model", {}))
        if "rng" in extra:
            torch.set_rng_state(extra["rng"]["torch"])
            np.random.set_state(extra["rng"]["numpy"])
            random.setstate(extra["rng"]["python"])
