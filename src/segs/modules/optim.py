"""One Adam with named parameter groups, learning-rate schedules, and the swap of a parameter
for a longer or shorter one with its Adam moments carried over row by row (segs.modules.rows).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn


@dataclass
class LrSchedule:
    """Log-linear decay from `init` to `final` over `steps` (constant when final is None)."""

    init: float
    final: float | None = None
    steps: int = 30000
    delay: int = 0

    def __call__(self, step: int) -> float:
        if self.final is None or self.init <= 0 or self.final <= 0:
            return self.init
        t = min(max(step - self.delay, 0) / max(self.steps, 1), 1.0)
        return math.exp((1 - t) * math.log(self.init) + t * math.log(self.final))


def make_adam(groups: list[dict], eps: float = 1e-15) -> torch.optim.Adam:
    """groups: [{"name": str, "params": [Parameter, ...], "lr": float}, ...]. The fused kernel
    (CPU and CUDA) updates every parameter in one pass: 4-5x faster than the per-tensor loop here."""
    names = [g["name"] for g in groups]
    if len(set(names)) != len(names):
        raise ValueError(f"duplicate parameter group names: {names}")
    return torch.optim.Adam(groups, lr=0.0, eps=eps, fused=True)


def set_learning_rates(optimizer: torch.optim.Optimizer, schedules: dict[str, LrSchedule], step: int) -> None:
    for group in optimizer.param_groups:
        sched = schedules.get(group["name"])
        if sched is not None:
            group["lr"] = sched(step)


def swap_parameter(optimizer: torch.optim.Optimizer | None, old: nn.Parameter, new: nn.Parameter, fix) -> None:
    """Point the optimizer at `new` instead of `old`, mapping each moment tensor through fix()."""
    if optimizer is None:
        return
    for group in optimizer.param_groups:
        for i, p in enumerate(group["params"]):
            if p is old:
                group["params"][i] = new
                state = optimizer.state.pop(old, None)
                if state:
                    optimizer.state[new] = {
                        k: (fix(v) if torch.is_tensor(v) and v.shape == old.shape else v) for k, v in state.items()
                    }
                return
