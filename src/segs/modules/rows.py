"""The one owner of per-primitive rows (anchors or Gaussians): parameters, their Adam moments,
fixed positions, densification statistics and source-keyframe tags, aligned on the leading
dimension N and edited together by `add` / `keep` / `resize`.

A new per-primitive quantity is one more entry in the store's layout; growth, pruning, loop
correction and checkpoint loading then carry it without further edits.
"""
from __future__ import annotations

import torch
from torch import nn

from segs.modules.optim import swap_parameter

# kinds of buffer rows: "float" rows take the parameters' dtype, "index" rows are int64
FLOAT, INDEX = "float", "index"


class PrimitiveRows(nn.Module):
    """Rows aligned on N. params: name -> trailing shape (optimised: one Adam group
    "<prefix><name>" each); buffers: name -> (trailing shape, FLOAT | INDEX) (not optimised).

    Parameters and buffers are plain attributes of this module, so the state dict holds them as
    "<name>" and `model.to(device, dtype)` moves every row.
    """

    def __init__(self, params: dict[str, tuple[int, ...]], buffers: dict[str, tuple[tuple[int, ...], str]], prefix: str = ""):
        super().__init__()
        self.prefix = prefix
        self.param_shapes = dict(params)
        self.buffer_layout = dict(buffers)
        for name, shape in params.items():
            self.register_parameter(name, nn.Parameter(torch.zeros((0, *shape))))
        for name, (shape, kind) in buffers.items():
            self.register_buffer(name, torch.zeros((0, *shape), dtype=torch.int64 if kind == INDEX else torch.float32))

    def __len__(self) -> int:
        name = next(iter(self.param_shapes))
        return self._parameters[name].shape[0]

    def __getitem__(self, name: str) -> torch.Tensor:
        return getattr(self, name)

    def parameters_by_name(self) -> dict[str, nn.Parameter]:
        return {name: self._parameters[name] for name in self.param_shapes}

    def group_name(self, name: str) -> str:
        return f"{self.prefix}{name}"

    def groups(self, lrs: dict[str, float]) -> list[dict]:
        """Optimizer groups [{"name", "params": [one tensor], "lr"}] in name order (the order
        checkpoints of every version hold their Adam moments in)."""
        return [{"name": self.group_name(k), "params": [p], "lr": lrs[k]} for k, p in sorted(self.parameters_by_name().items())]

    @torch.no_grad()
    def add(self, rows: dict[str, torch.Tensor], optimizer: torch.optim.Optimizer | None) -> int:
        """Append M rows: every parameter must be given (name -> [M, ...]); a buffer not given starts
        at 0. Rows are cast to the stored tensors' dtype and device; new Adam moments are zero."""
        missing, unknown = set(self.param_shapes) - set(rows), set(rows) - set(self.param_shapes) - set(self.buffer_layout)
        if missing or unknown:
            raise ValueError(f"add needs every parameter of {sorted(self.param_shapes)}; "
                             f"missing {sorted(missing)}, unknown {sorted(unknown)}")
        lengths = {v.shape[0] for v in rows.values()}
        if len(lengths) != 1:
            raise ValueError(f"rows of different lengths: { {k: tuple(v.shape) for k, v in rows.items()} }")
        m = lengths.pop()
        for name, old in self.parameters_by_name().items():
            extra = rows[name].detach().to(device=old.device, dtype=old.dtype)
            new = nn.Parameter(torch.cat([old.detach(), extra], 0))
            swap_parameter(optimizer, old, new, lambda v, e=extra: torch.cat([v, torch.zeros_like(e)], 0))
            self._parameters[name] = new
        for name in self.buffer_layout:
            old = self._buffers[name]
            extra = rows[name].to(device=old.device, dtype=old.dtype) if name in rows else old.new_zeros((m, *old.shape[1:]))
            self._buffers[name] = torch.cat([old, extra], 0)
        return m

    @torch.no_grad()
    def keep(self, mask: torch.Tensor, optimizer: torch.optim.Optimizer | None) -> None:
        """Keep the rows where mask [N] bool is True, everywhere (moments of kept rows preserved)."""
        for name, old in self.parameters_by_name().items():
            new = nn.Parameter(old.detach()[mask].clone())
            swap_parameter(optimizer, old, new, lambda v: v[mask])
            self._parameters[name] = new
        for name in self.buffer_layout:
            self._buffers[name] = self._buffers[name][mask]

    def resize(self, n: int) -> None:
        """Zero rows of length n everywhere (before load_state_dict of a checkpoint with n rows)."""
        for name, old in self.parameters_by_name().items():
            self._parameters[name] = nn.Parameter(old.new_zeros((n, *old.shape[1:])))
        for name in self.buffer_layout:
            old = self._buffers[name]
            self._buffers[name] = old.new_zeros((n, *old.shape[1:]))

    @torch.no_grad()
    def assign(self, name: str, value: torch.Tensor, optimizer: torch.optim.Optimizer | None, reset_state: bool = False) -> None:
        """Overwrite one parameter in place with a tensor of its shape (e.g. opacity reset),
        optionally zeroing its Adam moments."""
        p = self._parameters[name]
        p.copy_(value)
        if reset_state and optimizer is not None and p in optimizer.state:
            for v in optimizer.state[p].values():
                if torch.is_tensor(v) and v.shape == p.shape:
                    v.zero_()
