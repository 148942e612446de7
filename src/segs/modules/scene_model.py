"""The interface every scene representation (plain 3D-GS, SEGS anchors) offers the mapper."""
from __future__ import annotations

import abc
from dataclasses import dataclass, field

import torch
from torch import nn

from segs.data.frame import Camera
from segs.modules import losses
from segs.modules.optim import LrSchedule


@dataclass
class View:
    """A camera to render: w2c [4,4] float32, intrinsics, and the training keyframe id (or None)."""

    w2c: torch.Tensor
    camera: Camera
    kf_id: int | None = None

    @property
    def K(self) -> torch.Tensor:
        """[3,3] float32 for the rasterizer, whose pixel centres are at +0.5 (gsplat's convention);
        Camera follows OpenCV (centres at integers), hence cx, cy + 0.5."""
        K = torch.as_tensor(self.camera.K, dtype=torch.float32).clone()
        K[0, 2] += 0.5
        K[1, 2] += 0.5
        return K

    @property
    def center(self) -> torch.Tensor:
        """[3] camera centre in world coordinates."""
        r, t = self.w2c[:3, :3], self.w2c[:3, 3]
        return -(r.T @ t)


@dataclass
class Decoded:
    """Gaussians of one view, in rasterize() layout.

    means [N,3], quats [N,4] wxyz, scales [N,3] (linear), opacities [N] in [0,1], colors [N,3].
    aux: model-specific bookkeeping for statistics (e.g. which anchor each Gaussian came from).
    """

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    colors: torch.Tensor
    aux: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return self.means.shape[0]


def frustum_mask(points: torch.Tensor, view: View, margin: float = 0.15, near: float = 0.01) -> torch.Tensor:
    """[N] bool: points [N,3] in front of the camera and inside the image (widened by margin)."""
    cam = points @ view.w2c[:3, :3].T + view.w2c[:3, 3]
    z = cam[:, 2]
    c = view.camera
    u = c.fx * cam[:, 0] / z.clamp_min(1e-6) + c.cx
    v = c.fy * cam[:, 1] / z.clamp_min(1e-6) + c.cy
    mu, mv = margin * c.width, margin * c.height
    return (z > near) & (u > -mu) & (u < c.width + mu) & (v > -mv) & (v < c.height + mv)


def upgrade_state_keys(state: dict, renames: dict[str, str], prefix: str = "") -> dict:
    """state with keys `prefix + old` renamed to `prefix + new` (old ending in "." : a prefix)."""
    out = {}
    for key, value in state.items():
        name = key.removeprefix(prefix) if key.startswith(prefix) else None
        for old, new in renames.items() if name is not None else ():
            if name == old or (old.endswith(".") and name.startswith(old)):
                key = prefix + new + name[len(old):]
                break
        out[key] = value
    return out


class SceneModel(nn.Module, abc.ABC):
    """What the Lightning module needs from a scene representation.

    Per-primitive tensors grow and shrink during training; every such edit goes through the one
    optimizer passed in, so the Adam moments of surviving rows are kept.
    """

    scene_extent: float = 1.0
    # the schedules' length in steps (model.total_steps): learning rates, densification windows,
    # and the mapper's coarse-to-fine phases
    total_steps: int
    # the steps of the current run (trainer.max_steps; set by the mapper as fit starts), which may
    # end inside the schedule (a coarse-to-fine run shorter than mapping.min_schedule_steps)
    run_steps: int | None = None
    # whether loss() reads the keyframes' depth; without it the mapper keeps no depth image
    uses_depth: bool = False
    # whether the Gaussians are decoded per view (opacity, shape, colour from the direction to the
    # camera, frustum-culled): a PLY of one decoding then differs from the map, and the export is
    # fitted to the views (GaussianMapperModule.fitted_cloud); plain 3D-GS writes its own parameters
    decodes_per_view: bool = False
    # state-dict names of checkpoints written before the PrimitiveRows store: old -> new, a name
    # ending in "." renames every key under it (see upgrade_state_keys)
    LEGACY_STATE_KEYS: dict[str, str] = {}
    # (1 - lambda) L1 + lambda D-SSIM of [H,W,3] images (losses.photometric); compile_step_code
    # replaces it on the instance with its torch.compile form
    photometric = staticmethod(losses.photometric)

    def compile_step_code(self) -> None:
        """torch.compile the tensor code every training step runs (mapping.compile): here the
        photometric loss; models extend it with their own (SegsModel: the Gaussians' assembly)."""
        self.photometric = torch.compile(losses.photometric)

    @abc.abstractmethod
    def add_points(self, xyz: torch.Tensor, rgb: torch.Tensor, kf_ids: torch.Tensor, optimizer) -> int:
        """New SLAM points xyz [M,3], colours rgb [M,3], creating kf ids [M]; returns primitives added."""

    @abc.abstractmethod
    def correct_map(self, transforms: dict[int, torch.Tensor], optimizer) -> int:
        """Move primitives created by each kf_id by a world-to-world similarity [4,4]; returns count moved."""

    def register_views(self, views: dict[int, torch.Tensor]) -> None:
        """Training keyframes and their current w2c [4,4] (for per-view embeddings); default: unused."""

    def checkpoint_state(self) -> dict[str, torch.Tensor]:
        """What a resumed run needs beside the parameters' state_dict (tensors); default: nothing."""
        return {}

    def load_checkpoint_state(self, state: dict[str, torch.Tensor]) -> None:
        """Restore checkpoint_state() (an empty dict: a checkpoint written before it existed)."""

    def upgrade_state(self, state: dict, prefix: str) -> dict:
        """A checkpoint's state_dict (this model's keys under `prefix`) made loadable into this
        model, for parts a model keeps or not by its config (default: as it is)."""
        return state

    @abc.abstractmethod
    def param_groups(self) -> list[dict]:
        """Optimizer groups [{"name", "params", "lr"}] (initial learning rates)."""

    @abc.abstractmethod
    def lr_schedules(self) -> dict[str, LrSchedule]:
        """Group name -> schedule (groups without one keep their initial rate)."""

    @abc.abstractmethod
    def decode(self, view: View, step: int, averaged: bool = False) -> Decoded:
        """Gaussians to render for this view. averaged: a render outside training (evaluation,
        viewer, export), decoded with weights averaged over the latest steps where the model keeps
        such an average (SEGS: segs.modules.decoder_average), else as in training."""

    def after_step(self) -> None:
        """After each optimizer step (default: nothing; SEGS: the decoder average's update)."""

    @abc.abstractmethod
    def loss(self, render, gt: torch.Tensor, decoded: Decoded, step: int, gt_depth: torch.Tensor | None) -> dict:
        """Loss terms for one rendered view; must contain "total" (scalar tensor)."""

    @abc.abstractmethod
    def after_backward(self, decoded: Decoded, render, step: int) -> None:
        """Accumulate densification statistics from gradients (means2d.grad etc.)."""

    @abc.abstractmethod
    def maintain(self, step: int, optimizer) -> dict[str, float]:
        """Densify / prune / reset at this step; returns numbers to log."""

    @abc.abstractmethod
    def count_active(self, view: View, threshold: float = 0.005) -> int:
        """Gaussians of this view whose opacity exceeds threshold (compactness reporting)."""

    @abc.abstractmethod
    def counts(self) -> dict[str, float]:
        """{"anchors", "gaussians", "params", "mb"} of the current model."""

    @abc.abstractmethod
    def resize_for_state(self, state_dict: dict[str, torch.Tensor]) -> None:
        """Re-create per-primitive tensors with the checkpoint's sizes before loading it."""

    @abc.abstractmethod
    def decode_all(self, view: View) -> Decoded:
        """Every primitive decoded for this view's direction and appearance, without culling
        (no gradient): the Gaussians export_ply writes."""

    @abc.abstractmethod
    def export_ply(self, path, view: View) -> int:
        """Write the Gaussians decoded for `view` as a standard 3D-GS PLY; returns their count."""
