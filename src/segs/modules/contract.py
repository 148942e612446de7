"""The bridge contract: what the SLAM bridge, the evaluation, the callbacks and the viewer may use
of the mapper (the `GaussianMapper` protocol), and the records that cross it.

Poses are world-to-camera [4,4] float32 tensors (gsplat's viewmat); the bridge converts the
frontend's numpy poses once, the mapper stores them as given.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np
import torch

from segs.data.frame import Camera


@dataclass
class TrainingView:
    """One training view of the mapper: the image of a SLAM keyframe (kf_id) and its refreshed pose.

    image: [H,W,3] uint8 (kept compact; `rgb()` gives float [H,W,3] in [0,1])
    depth: [H,W] float32 metres (0 = invalid) or None
    w2c:   [4,4] float32 world-to-camera pose (refreshed by the frontend)
    """

    kf_id: int
    frame_index: int
    timestamp: float
    image: torch.Tensor
    w2c: torch.Tensor
    camera: Camera
    depth: torch.Tensor | None = None

    def rgb(self) -> torch.Tensor:
        """[H,W,3] float32 in [0,1]."""
        return self.image.float() / 255.0


def to_uint8(rgb: torch.Tensor) -> torch.Tensor:
    """[H,W,3] float in [0,1] -> uint8."""
    return (rgb.clamp(0, 1) * 255.0 + 0.5).to(torch.uint8)


@dataclass
class MapCounts:
    """Size of the map: training views, anchors (0 for plain 3D-GS), Gaussians (anchors * k for
    SEGS), optimised parameters and the model's size in MB."""

    training_views: int
    anchors: int
    gaussians: int
    params: int
    mb: float


MIN_OPACITY = 1.0 / 255.0  # below it a Gaussian cannot change an 8-bit pixel: viewers skip it, the PLY's fit drops it


@dataclass
class GaussianCloud:
    """Every Gaussian of the map, on the CPU in float32, as `export_ply` writes them (decoded with
    the first training view's direction and appearance for SEGS).

    means [N,3]; quats [N,4] wxyz, unit; scales [N,3] linear; opacities [N] in (0,1); colors [N,3]
    in [0,1].
    """

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    colors: torch.Tensor

    def __len__(self) -> int:
        return self.means.shape[0]


@runtime_checkable
class GaussianMapper(Protocol):
    """The mapper as the bridge, the evaluation, the callbacks and the viewer see it."""

    iteration_ms: list[float]  # wall time of every training step so far (resumed runs included)
    raster_backend: str | None  # the rasterizer backend of the latest render ("cpu", "cuda", "torch"); None before one
    uses_depth: bool  # whether training reads TrainingView.depth (without it the bridge keeps no depth)
    compiled: bool  # whether the model's per-step tensor code runs compiled (mapping.compile)

    def add_keyframes(self, views: list[TrainingView]) -> None:
        """New training views (their poses are registered here, once)."""

    def update_poses(self, poses: dict[int, torch.Tensor]) -> None:
        """Refreshed w2c [4,4] float32 by kf_id (ids without a training view are ignored)."""

    def add_points(self, xyz: torch.Tensor, rgb: torch.Tensor, kf_ids: torch.Tensor) -> int:
        """New SLAM points xyz [M,3], colours [M,3] in [0,1], creating kf ids [M] int64; returns
        the primitives added."""

    def correct_map(self, transforms: dict[int, torch.Tensor]) -> int:
        """Loop closure: move what each kf_id created by a world-to-world similarity [4,4]."""

    def counts(self) -> MapCounts:
        """The map's size now."""

    def first_view(self) -> TrainingView | None:
        """The training view of the lowest kf_id (None before the first)."""

    def render_image(self, w2c: np.ndarray | torch.Tensor, camera: Camera, kf_id: int | None = None) -> dict:
        """{"image" [H,W,3], "depth" [H,W], "alpha" [H,W]} on the CPU, rendered at w2c [4,4]."""

    def count_active(self, w2c: np.ndarray | torch.Tensor, camera: Camera, threshold: float) -> int:
        """Gaussians of the view at w2c whose opacity exceeds threshold (compactness)."""

    def training_views(self) -> list[TrainingView]:
        """The training views in arrival order (the records themselves, with their current poses)."""

    def gaussians(self, w2c: np.ndarray | torch.Tensor | None = None, camera: Camera | None = None) -> GaussianCloud | None:
        """The Gaussians, copied to the CPU (the viewer's snapshot), None before the first training
        view. w2c [4,4] given: those a render from that camera (intrinsics `camera`, default the
        first training view's) draws, decoded for it (SEGS: the anchors in its frustum, with its
        direction and a novel view's appearance). Without: every Gaussian as export_ply writes them."""

    def export_ply(self, path: str | Path, cloud: GaussianCloud | None = None) -> int:
        """Write `cloud` (from fitted_cloud) or, without one, the model's own export (SEGS: decoded
        with the first view's direction) as a 3D-GS PLY; returns the Gaussians written (0 and no
        file without a training view)."""

    def fitted_cloud(self, steps: int, progress: Callable[[int], None] | None = None) -> GaussianCloud | None:
        """A model that decodes per view (SEGS): its Gaussians fitted for `steps` steps to the
        training views as a standard 3D-GS renderer draws them; None for a model exported as it
        is (plain 3D-GS) or before a training view."""

    def render_cloud(self, gaussians: tuple[torch.Tensor, ...], w2c: np.ndarray | torch.Tensor, camera: Camera) -> torch.Tensor:
        """[H,W,3], not clamped: Gaussians (means, unit quats, scales, opacities, colours) drawn at
        w2c [4,4] as a standard 3D-GS renderer draws them."""
