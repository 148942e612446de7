"""Decoder average: the decoders' weights averaged over the latest training steps, for renders
outside training.

SEGS's Gaussians come out of small MLPs (Scaffold-GS's opacity, covariance and colour decoders)
and AfME's pose encoder. Each training step moves them towards the one view it trained on: with
the learning rates of the schedule's first half a render from a held-out pose swings by several
tenths of a dB from one step to the next. Renders outside training
(evaluation, viewer, logged images, the PLY export) therefore decode with an exponential moving
average of these weights, `decay` per step (Polyak averaging with torch's
`torch.optim.swa_utils` EMA function); training decodes with the live weights. The anchors'
own rows (features, offsets, scales) are not averaged: their count changes with every growth
step. (docs/decisions/039-decoder-average.md.)
"""
from __future__ import annotations

import copy

import torch
from torch import nn
from torch.optim.swa_utils import get_ema_multi_avg_fn


class DecoderAverage(nn.Module):
    """An exponential moving average of `decoders` (named modules; shapes fixed for the run).

    decay: weight of the average kept at each update, in [0, 1). `averaged[name]` is the averaged
    copy of `decoders[name]` (no gradient); it starts as the weights given here. An update reads
    nothing back from the device (one fused lerp, torch's EMA function).
    """

    def __init__(self, decoders: dict[str, nn.Module], decay: float):
        super().__init__()
        if not 0.0 <= decay < 1.0:
            raise ValueError(f"decay must be in [0, 1), got {decay}")
        self.decay = decay
        self.averaged = copy.deepcopy(nn.ModuleDict(decoders)).requires_grad_(False)
        self._lerp = get_ema_multi_avg_fn(decay)

    @torch.no_grad()
    def update(self, decoders: dict[str, nn.Module]) -> None:
        """One step of the average towards the live `decoders` (the same names and shapes)."""
        live = [p.detach() for name in self.averaged for p in decoders[name].parameters()]
        self._lerp([p for m in self.averaged.values() for p in m.parameters()], live, None)

    def filled_state(self, state: dict[str, torch.Tensor], prefix: str, sources: dict[str, str]) -> dict[str, torch.Tensor]:
        """`state` (a state_dict holding this module's keys under `prefix`, or none of them) with
        the missing keys made from the live decoders' weights in it: sources maps each decoder's
        name to its module's key prefix in `state` (a checkpoint written before the average
        existed, or with it off, restores with the average equal to the live weights)."""
        if any(k.startswith(prefix) for k in state):
            return state
        out = dict(state)
        for name, src in sources.items():
            for key, value in state.items():
                if key.startswith(src):
                    out[f"{prefix}averaged.{name}.{key[len(src):]}"] = value.detach().clone()
        return out
