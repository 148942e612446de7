"""Training views of the mapper (segs.modules.contract.TrainingView: keyframe images with
refreshable poses), kept by kf_id, and the order in which training draws them."""
from __future__ import annotations

import random

import torch

from segs.data.frame import Camera
from segs.modules.contract import TrainingView


class ViewSampler:
    """Random training-view order with a per-keyframe budget (reference implementation's rule).

    Each keyframe gets `budget` uses when it arrives; views are drawn uniformly among keyframes
    with budget left; when every budget is spent, every keyframe gets one more use.
    """

    def __init__(self, budget: int = 2, seed: int = 0):
        if budget < 1:
            raise ValueError(f"view budget must be >= 1, got {budget}")
        self.budget = budget
        self.remaining: dict[int, int] = {}
        self.rng = random.Random(seed)

    def add(self, kf_id: int) -> None:
        self.remaining.setdefault(kf_id, self.budget)

    def next(self) -> int:
        if not self.remaining:
            raise RuntimeError("no keyframes to sample a training view from")
        live = sorted(k for k, n in self.remaining.items() if n > 0)
        if not live:
            for k in self.remaining:
                self.remaining[k] += 1
            live = sorted(self.remaining)
        kf_id = self.rng.choice(live)
        self.remaining[kf_id] -= 1
        return kf_id

    def state_dict(self) -> dict:
        return {"budget": self.budget, "remaining": dict(self.remaining), "rng": self.rng.getstate()}

    def load_state_dict(self, state: dict) -> None:
        self.budget = state["budget"]
        self.remaining = {int(k): int(v) for k, v in state["remaining"].items()}
        self.rng.setstate(state["rng"])


class TrainingViews:
    """Training views by kf_id, in arrival order, with the view sampler."""

    def __init__(self, budget: int = 2, seed: int = 0):
        self.frames: dict[int, TrainingView] = {}
        self.sampler = ViewSampler(budget, seed)

    def __len__(self) -> int:
        return len(self.frames)

    def __contains__(self, kf_id: int) -> bool:
        return kf_id in self.frames

    def __getitem__(self, kf_id: int) -> TrainingView:
        return self.frames[kf_id]

    def add(self, kf: TrainingView) -> None:
        self.frames[kf.kf_id] = kf
        self.sampler.add(kf.kf_id)

    def update_pose(self, kf_id: int, w2c: torch.Tensor) -> None:
        """w2c [4,4] float32 (as the bridge made it); unknown kf_ids are ignored."""
        if kf_id in self.frames:
            self.frames[kf_id].w2c = w2c

    def first(self) -> TrainingView | None:
        """The view of the lowest kf_id, None when there is none."""
        return self.frames[min(self.frames)] if self.frames else None

    def sample(self) -> TrainingView:
        return self.frames[self.sampler.next()]

    def state_dict(self) -> dict:
        frames = [
            {
                "kf_id": k.kf_id,
                "frame_index": k.frame_index,
                "timestamp": k.timestamp,
                "image": k.image,
                "w2c": k.w2c,
                "camera": k.camera.__dict__,
                "depth": k.depth,
            }
            for k in self.frames.values()
        ]
        return {"frames": frames, "sampler": self.sampler.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        self.frames = {}
        for f in state["frames"]:
            kf = TrainingView(**{**f, "camera": Camera(**f["camera"])})
            self.frames[kf.kf_id] = kf
        self.sampler.load_state_dict(state["sampler"])
