"""One Adam with named parameter groups, and in-place growth / pruning of per-primitive tensors.

Growth and pruning replace a parameter by a longer or shorter one; its Adam moments are carried
over row by row (new rows start at zero), so surviving primitives keep their optimizer state.
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
    """groups: [{"name": str, "params": [Parameter, ...], "lr": float}, ...]"""
    names = [g["name"] for g in groups]
    if len(set(names)) != len(names):
        raise ValueError(f"duplicate parameter group names: {names}")
    return torch.optim.Adam(groups, lr=0.0, eps=eps)


def set_learning_rates(optimizer: torch.optim.Optimizer, schedules: dict[str, LrSchedule], step: int) -> None:
    for group in optimizer.param_groups:
        sched = schedules.get(group["name"])
        if sched is not None:
            group["lr"] = sched(step)


def _swap(optimizer: torch.optim.Optimizer | None, old: nn.Parameter, new: nn.Parameter, fix) -> None:
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


class PrimitiveParams(nn.Module):
    """Per-primitive parameters sharing the leading dimension N (anchors or Gaussians).

    tensors: name -> [N, ...]; each becomes its own optimizer group "<prefix><name>".
    """

    def __init__(self, shapes: dict[str, tuple[int, ...]], prefix: str = ""):
        super().__init__()
        self.prefix = prefix
        self.shapes = dict(shapes)
        self.params = nn.ParameterDict({k: nn.Parameter(torch.zeros((0, *s))) for k, s in shapes.items()})

    def __len__(self) -> int:
        return next(iter(self.params.values())).shape[0] if self.params else 0

    def __getitem__(self, name: str) -> nn.Parameter:
        return self.params[name]

    def group_name(self, name: str) -> str:
        return f"{self.prefix}{name}"

    def groups(self, lrs: dict[str, float]) -> list[dict]:
        return [{"name": self.group_name(k), "params": [p], "lr": lrs[k]} for k, p in self.params.items()]

    def extend(self, rows: dict[str, torch.Tensor], optimizer: torch.optim.Optimizer | None) -> None:
        """Append rows (name -> [M, ...]) to every tensor; new Adam moments are zero."""
        if set(rows) != set(self.params):
            raise ValueError(f"extend needs exactly {sorted(self.params)}, got {sorted(rows)}")
        m = {v.shape[0] for v in rows.values()}
        if len(m) != 1:
            raise ValueError(f"rows of different lengths: { {k: v.shape for k, v in rows.items()} }")
        for k, old in list(self.params.items()):
            extra = rows[k].detach().to(device=old.device, dtype=old.dtype)
            new = nn.Parameter(torch.cat([old.detach(), extra], 0))
            _swap(optimizer, old, new, lambda v, e=extra: torch.cat([v, torch.zeros_like(e)], 0))
            self.params[k] = new

    def keep(self, mask: torch.Tensor, optimizer: torch.optim.Optimizer | None) -> None:
        """Keep rows where mask [N] bool is True (moments of kept rows preserved)."""
        for k, old in list(self.params.items()):
            new = nn.Parameter(old.detach()[mask].clone())
            _swap(optimizer, old, new, lambda v: v[mask])
            self.params[k] = new

    def assign(self, name: str, value: torch.Tensor, optimizer: torch.optim.Optimizer | None, reset_state: bool = False) -> None:
        """Overwrite one tensor in place of the same shape (e.g. opacity reset), optionally zeroing moments."""
        old = self.params[name]
        with torch.no_grad():
            old.copy_(value)
        if reset_state and optimizer is not None and old in optimizer.state:
            for v in optimizer.state[old].values():
                if torch.is_tensor(v) and v.shape == old.shape:
                    v.zero_()

    def resize_(self, n: int) -> None:
        """Re-create empty tensors of length n (before load_state_dict of a checkpoint)."""
        for k, s in self.shapes.items():
            old = self.params[k]
            self.params[k] = nn.Parameter(torch.zeros((n, *s), dtype=old.dtype, device=old.device))
