"""Structured 3D Gaussians (Scaffold-GS): fixed anchors whose k Gaussians are decoded by MLPs.

Per anchor: a fixed position (a buffer, never optimised), a feature f [F], k offsets [k,3] and
6 log-scales l (3 for offsets, 3 for Gaussian scales). For the anchors inside the view frustum:
  x        = [f, d (, delta)]        d = (anchor - camera centre)/delta, delta = its length
  opacity  = tanh(M_alpha(x))        [k]; Gaussians with opacity <= 0 are dropped
  cov      = M_cov(x)                [7k]: scale = exp(l)[3:6] * sigmoid(cov[:3]), rot = normalize(cov[3:7])
  colour   = sigmoid(M_c([x, e]))    [3k]; e = appearance embedding (AfME / AE), absent when A = 0
  mean     = anchor + offset * exp(l)[0:3]
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import torch
import torch.nn.functional as F
from torch import nn

from segs.modules.rows import FLOAT, INDEX, PrimitiveRows
from segs.modules.scene_model import Decoded, View, frustum_mask


def mlp(n_in: int, hidden: int, n_out: int) -> nn.Sequential:
    """Linear-ReLU-Linear decoder."""
    return nn.Sequential(nn.Linear(n_in, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, n_out))


@dataclass
class DecodeInfo:
    """Where each rendered Gaussian came from (for densification statistics).

    visible: [V] long indices of the anchors decoded for this view
    keep:    [M] long indices into the V*k slots (anchor-major) of the rendered Gaussians, in order
    opacity: [V,k] raw tanh opacities (detached), for the anchor opacity statistics
    """

    visible: torch.Tensor
    keep: torch.Tensor
    opacity: torch.Tensor

    def slots(self, k: int) -> torch.Tensor:
        """[M] global slot ids (anchor index * k + offset index) of the rendered Gaussians."""
        return self.visible[self.keep // k] * k + self.keep % k


def decode_front(xyz_all: torch.Tensor, features: torch.Tensor, visible: torch.Tensor, center: torch.Tensor,
                 first: tuple[tuple[torch.Tensor, torch.Tensor], ...], opacity_out: tuple[torch.Tensor, torch.Tensor],
                 embedding: torch.Tensor | None, use_distance: bool) -> tuple[torch.Tensor, ...]:
    """The decoders' input and hidden layers for the V visible anchors, and their opacities.

    xyz_all [N,3] every anchor's position; visible [V] the visible ones' indices; features [V,F]
    their features (gathered by the caller: torch.compile treats a parameter's shape as fixed, and
    the feature rows change size with every growth round); center [3] the camera centre; first:
    (weight, bias) of the opacity, covariance and colour decoders' first layers (the colour one
    also takes the embedding); opacity_out: (weight [k,hidden], bias [k]) of the opacity decoder's
    output layer; embedding [A] or None. The three first layers share their input, so they run as
    one matrix product, the embedding's part of the colour layer as a bias.
    Returns xyz [V,3], h_cov [V,hidden], h_col [V,hidden], opacity [V,k] = tanh(M_alpha(x)).
    A pure function of tensors, like `assemble` (AnchorField.compile_decoding).
    """
    pick = torch.index_select
    xyz = pick(xyz_all, 0, visible)
    rel = xyz - center
    dist = rel.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    x = torch.cat([features, rel / dist] + ([dist] if use_distance else []), -1)
    (w_op, b_op), (w_cov, b_cov), (w_col, b_col) = first
    n_in = x.shape[1]
    weight = torch.cat([w_op, w_cov, w_col[:, :n_in]], 0)
    if embedding is not None:
        b_col = b_col + w_col[:, n_in:] @ embedding.to(x)
    h_op, h_cov, h_col = torch.relu(torch.addmm(torch.cat([b_op, b_cov, b_col]), x, weight.T)).split(w_op.shape[0], dim=1)
    return xyz, h_cov, h_col, torch.tanh(torch.addmm(opacity_out[1], h_op, opacity_out[0].T))


def assemble(xyz: torch.Tensor, log_scales: torch.Tensor, offsets: torch.Tensor, h_cov: torch.Tensor, h_col: torch.Tensor,
             opacity: torch.Tensor, keep: torch.Tensor, w_cov: torch.Tensor, b_cov: torch.Tensor, w_col: torch.Tensor,
             b_col: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """The rendered Gaussians of the visible anchors (module docstring): V visible anchors, k
    Gaussians each, M = len(keep) of the V*k slots rendered (opacity > 0).

    xyz [V,3], log_scales [V,6], offsets [V,k,3] of the visible anchors; h_cov, h_col [V,hidden]
    hidden layers of the covariance and colour decoders, whose output layers are (w_cov [7k,hidden],
    b_cov [7k]) and (w_col [3k,hidden], b_col [3k]); opacity [V,k]; keep [M] slot indices.
    Returns means [M,3], quats [M,4], scales [M,3], opacities [M], colors [M,3]. A pure function
    of tensors, so torch.compile can fuse it (AnchorField.compile_decoding).
    """
    pick = torch.index_select
    k = opacity.shape[1]
    anchor = keep // k
    cov = pick(torch.addmm(b_cov, h_cov, w_cov.T).reshape(-1, 7), 0, keep)
    color = torch.sigmoid(pick(torch.addmm(b_col, h_col, w_col.T).reshape(-1, 3), 0, keep))
    scale = pick(torch.exp(log_scales), 0, anchor)  # [M,6]
    offs = pick(offsets.reshape(-1, 3), 0, keep)
    means = pick(xyz, 0, anchor) + offs * scale[:, :3]
    return (means, F.normalize(cov[:, 3:7], dim=-1), scale[:, 3:] * torch.sigmoid(cov[:, :3]),
            pick(opacity.reshape(-1), 0, keep), color)


class AnchorField(nn.Module):
    """Anchors (one PrimitiveRows store) + the three Scaffold-GS decoders (hidden width `hidden`).

    Rows per anchor: parameters features [F], offsets [k,3], log_scales [6]; buffers xyz [3]
    (fixed position), kf_tag (the keyframe whose points created it, for loop corrections) and
    the densification statistics opacity_accum, anchor_visits, grad_accum [k], grad_visits [k].
    """

    def __init__(self, k: int, feature_dim: int, hidden: int, appearance_dim: int, use_distance: bool, frustum_margin: float):
        super().__init__()
        self.k, self.feature_dim, self.appearance_dim = k, feature_dim, appearance_dim
        self.use_distance, self.frustum_margin = use_distance, frustum_margin
        n_in = feature_dim + 3 + int(use_distance)
        self.rows = PrimitiveRows(
            params={"features": (feature_dim,), "offsets": (k, 3), "log_scales": (6,)},
            buffers={"xyz": ((3,), FLOAT), "kf_tag": ((), INDEX), "opacity_accum": ((), FLOAT), "anchor_visits": ((), FLOAT),
                     "grad_accum": ((k,), FLOAT), "grad_visits": ((k,), FLOAT)},
            prefix="anchor.",
        )  # fmt: skip
        self.mlp_opacity = mlp(n_in, hidden, k)
        self.mlp_cov = mlp(n_in, hidden, 7 * k)
        self.mlp_color = mlp(n_in + appearance_dim, hidden, 3 * k)
        # the decoding's pure tensor functions; compile_decoding() replaces them with compiled forms
        self.in_frustum, self.decode_front, self.assemble = frustum_mask, decode_front, assemble

    def __len__(self) -> int:
        return len(self.rows)

    @property
    def xyz(self) -> torch.Tensor:
        """[N,3] anchor positions (a buffer row of the store; edit in place)."""
        return self.rows.xyz

    def decoders(self) -> dict[str, nn.Sequential]:
        """The three decoders by name (the optimizer's group names)."""
        return {"mlp_opacity": self.mlp_opacity, "mlp_cov": self.mlp_cov, "mlp_color": self.mlp_color}

    def decoder_groups(self) -> dict[str, list[nn.Parameter]]:
        return {name: list(m.parameters()) for name, m in self.decoders().items()}

    def add(self, xyz: torch.Tensor, features: torch.Tensor, log_scales: torch.Tensor, kf_tag: torch.Tensor, optimizer) -> int:
        """Append anchors: positions [M,3], features [M,F], log-scales [M,6], source kf ids [M];
        offsets and statistics start at 0."""
        offsets = features.new_zeros(xyz.shape[0], self.k, 3)
        return self.rows.add({"xyz": xyz, "features": features, "offsets": offsets, "log_scales": log_scales, "kf_tag": kf_tag}, optimizer)

    def gaussian_positions(self) -> torch.Tensor:
        """[N,k,3] world positions of every anchor's k Gaussians (no gradient)."""
        scale = torch.exp(self.rows["log_scales"].detach()[:, :3])
        return self.xyz[:, None, :] + self.rows["offsets"].detach() * scale[:, None, :]

    def decode(self, view: View, embedding: torch.Tensor | None, cull: bool = True,
               decoders: Mapping[str, nn.Module] | None = None) -> tuple[Decoded, DecodeInfo]:  # fmt: skip
        """Decode the Gaussians of the anchors inside the view frustum (all anchors if not cull).

        embedding: [A] appearance embedding or None. The first layers of the three decoders
        share their input, so they run as one matrix product; the embedding's contribution to
        the colour decoder is the same for every anchor and enters as a bias. decoders: modules
        shaped as `self.decoders()` to decode with instead (the decoder average).
        """
        mlps = self.decoders() if decoders is None else decoders
        m_opacity, m_cov, m_color = mlps["mlp_opacity"], mlps["mlp_cov"], mlps["mlp_color"]
        if cull:
            visible = torch.nonzero(self.in_frustum(self.xyz, view, self.frustum_margin)).squeeze(1)
        else:
            visible = torch.arange(len(self), device=self.xyz.device)
        # index_select, not t[idx]: its backward is index_add_, several times faster on the CPU
        # than the accumulating index_put_ of advanced indexing (the same sums)
        pick = torch.index_select
        first = tuple((m[0].weight, m[0].bias) for m in (m_opacity, m_cov, m_color))
        xyz, h_cov, h_col, opacity = self.decode_front(
            self.xyz, pick(self.rows["features"], 0, visible), visible, view.center.to(self.xyz), first,
            (m_opacity[2].weight, m_opacity[2].bias), embedding if self.appearance_dim else None, self.use_distance,
        )  # fmt: skip
        keep = torch.nonzero(opacity.detach().reshape(-1) > 0).squeeze(1)  # rendered slots
        lin_cov, lin_col = m_cov[2], m_color[2]
        decoded = Decoded(*self.assemble(xyz, pick(self.rows["log_scales"], 0, visible), pick(self.rows["offsets"], 0, visible),
                                         h_cov, h_col, opacity, keep, lin_cov.weight, lin_cov.bias, lin_col.weight, lin_col.bias))
        return decoded, DecodeInfo(visible, keep, opacity.detach())

    def compile_decoding(self) -> None:
        """Replace the frustum test, `decode_front` and `assemble` with their torch.compile forms
        (dynamic shapes: one compilation serves every anchor count; no parameter row is an
        argument, so growth and pruning, which resize them, compile nothing again): the gathers,
        activations and comparisons fuse into a few kernels forward and backward, fewer launches
        per step on a GPU. Values agree with the eager forms to float rounding."""
        self.in_frustum = torch.compile(frustum_mask, dynamic=True)
        self.decode_front = torch.compile(decode_front, dynamic=True)
        self.assemble = torch.compile(assemble, dynamic=True)
