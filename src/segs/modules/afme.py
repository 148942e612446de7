"""AfME: appearance from motion — a camera pose -> appearance embedding for the colour decoder.

The paper's encoder is a single linear layer on the world-to-camera pose as 7 numbers
[t (3), q (4, wxyz)]. The quaternion is canonicalized to w >= 0 (q and -q are the same
rotation; the authors' code does not handle this). At test time the test frame's estimated pose
goes in; nothing is fitted on test images.

Variants (config `model.appearance.kind`): "linear" (the paper), "mlp" (ours: translation
divided by the scene extent, Linear-ReLU-Linear), "ae" (the ablation: a learned embedding per training
keyframe, NeRF-W / Scaffold-GS; a test frame uses the embedding of the training keyframe whose
camera centre is nearest — AE cannot embed unseen views, and this is the most favourable
choice that uses no test image), "none" (no embedding).
"""
from __future__ import annotations

import torch
from torch import nn

from segs.errors import LimitError
from segs.modules.geometry import rotmat_to_quat

KINDS = ("linear", "mlp", "ae", "none")


def canonical_pose(t: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """[7] = [t (3), q / |q| with w >= 0] — q and -q (the same rotation) give the same vector."""
    q = q / q.norm().clamp_min(1e-12)
    return torch.cat([t, torch.where(q[0] < 0, -q, q)])


def pose_vector(w2c: torch.Tensor) -> torch.Tensor:
    """World-to-camera [4,4] -> [7] = [t, q (wxyz, w >= 0)]."""
    return canonical_pose(w2c[:3, 3], rotmat_to_quat(w2c[:3, :3]).to(w2c))


class AppearanceEncoder(nn.Module):
    """Pose (or training-view id) -> embedding [A]."""

    def __init__(self, kind: str = "linear", dim: int = 32, hidden: int = 32, max_views: int = 4096):
        super().__init__()
        if kind not in KINDS:
            raise ValueError(f"model.appearance.kind must be one of {KINDS}, got {kind!r}")
        self.kind, self.dim = kind, (0 if kind == "none" else dim)
        self._poses: dict[int, tuple[torch.Tensor, ...]] = {}  # kf_id -> (w2c, pose vector, its canonical_pose)
        self.scene_extent = 1.0
        if kind == "linear":
            self.net = nn.Linear(7, dim)
        elif kind == "mlp":
            self.net = nn.Sequential(nn.Linear(7, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, dim))
        elif kind == "ae":
            self.table = nn.Embedding(max_views, dim)
            nn.init.zeros_(self.table.weight)
            self.view_rows: dict[int, int] = {}
            self.register_buffer("centers", torch.zeros(0, 3))
            self.register_buffer("center_ids", torch.zeros(0, dtype=torch.long))

    def register_view(self, kf_id: int, center: torch.Tensor) -> None:
        """AE only: remember a training keyframe (its row and camera centre [3])."""
        if self.kind != "ae":
            return
        if kf_id not in self.view_rows:
            if len(self.view_rows) >= self.table.num_embeddings:
                raise LimitError(f"AE table full ({self.table.num_embeddings} training views): raise model.appearance.max_views")
            self.view_rows[kf_id] = len(self.view_rows)
            self.centers = torch.cat([self.centers, center.reshape(1, 3).to(self.centers)])
            self.center_ids = torch.cat([self.center_ids, torch.tensor([kf_id], device=self.center_ids.device)])
        else:
            i = int(torch.nonzero(self.center_ids == kf_id)[0, 0])
            self.centers[i] = center.to(self.centers)

    def weights(self) -> nn.Module | None:
        """The learned part: the pose encoder (linear, mlp), the embedding table (ae), or None."""
        if self.kind == "none":
            return None
        return self.table if self.kind == "ae" else self.net

    def forward(self, w2c: torch.Tensor, kf_id: int | None, weights: nn.Module | None = None) -> torch.Tensor | None:
        """Embedding [A] for a view, or None when appearance is off. weights: a module shaped as
        `self.weights()` to use instead of it (the decoder average, segs.modules.decoder_average)."""
        if self.kind == "none":
            return None
        if self.kind == "ae":
            return (self.table if weights is None else weights).weight[self._row(w2c, kf_id)]
        return self._embed_canonical(self._kept(w2c, kf_id)[1], weights)

    def _kept(self, w2c: torch.Tensor, kf_id: int | None) -> tuple[torch.Tensor, torch.Tensor]:
        """(pose_vector(w2c) [7], embed's input: its canonical_pose [7]), kept per training view
        while its pose tensor is the same object (the mapper replaces it when the pose changes):
        a training step converts no rotation and canonicalizes nothing."""
        hit = self._poses.get(kf_id) if kf_id is not None else None
        if hit is not None and hit[0] is w2c:
            return hit[1], hit[2]
        pose = pose_vector(w2c)
        x = canonical_pose(pose[:3], pose[3:])
        if kf_id is not None:
            self._poses[kf_id] = (w2c, pose, x)
        return pose, x

    def embed(self, pose: torch.Tensor) -> torch.Tensor:
        """AfME on a pose vector [7] = [t, q wxyz] (canonicalized here) -> [A]."""
        return self._embed_canonical(canonical_pose(pose[:3], pose[3:]))

    def _embed_canonical(self, x: torch.Tensor, weights: nn.Module | None = None) -> torch.Tensor:
        """AfME on a canonicalized pose vector [7] -> [A] (with `weights` in place of self.net)."""
        if self.kind == "mlp":
            x = torch.cat([x[:3] / max(self.scene_extent, 1e-6), x[3:]])
        return (self.net if weights is None else weights)(x)

    def _row(self, w2c: torch.Tensor, kf_id: int | None) -> int:
        if kf_id is not None and kf_id in self.view_rows:
            return self.view_rows[kf_id]
        if not self.view_rows:
            return 0
        center = -(w2c[:3, :3].T @ w2c[:3, 3])
        nearest = int(torch.argmin((self.centers - center.to(self.centers)).norm(dim=-1)))
        return self.view_rows[int(self.center_ids[nearest])]

    def extra_state(self) -> dict:
        return {"view_rows": dict(getattr(self, "view_rows", {}))}
