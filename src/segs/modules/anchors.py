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


def assemble(xyz: torch.Tensor, log_scales: torch.Tensor, offsets: torch.Tensor, h_cov: torch.Tensor, h_col: torch.Tensor,
             opacity: torch.Tensor, keep: torch.Tensor, w_cov: torch.Tensor, b_cov: torch.Tensor, w_col: torch.Tensor,
             b_col: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """The rendered Gaussians of the visible anchors (module docstring): V visible anchors, k
    Gaussians each, M = len(keep) of the V*k slots rendered (opacity > 0).

    xyz [V,3], log_scales [V,6], offsets [V,k,3] of the visible anchors; h_cov, h_col [V,hidden]
    hidden layers of the covariance and colour decoders, whose output layers are (w_cov [7k,hidden],
    b_cov [7k]) and (w_col [3k,hidden], b_col [3k]); opacity [V,k]; keep [M] slot indices.
    Returns means [M,3], quats [M,4], scales [M,3], opacities [M], colors [M,3]. A pure function
    of tensors, so torch.compile can fuse it (AnchorField.compile_assembly).
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
        self.assemble = assemble  # the Gaussians from the decoder outputs; compile_assembly() fuses it

    def __len__(self) -> int:
        return len(self.rows)

    @property
    def xyz(self) -> torch.Tensor:
        """[N,3] anchor positions (a buffer row of the store; edit in place)."""
        return self.rows.xyz

    def decoder_groups(self) -> dict[str, list[nn.Parameter]]:
        return {
            "mlp_opacity": list(self.mlp_opacity.parameters()),
            "mlp_cov": list(self.mlp_cov.parameters()),
            "mlp_color": list(self.mlp_color.parameters()),
        }

    def add(self, xyz: torch.Tensor, features: torch.Tensor, log_scales: torch.Tensor, kf_tag: torch.Tensor, optimizer) -> int:
        """Append anchors: positions [M,3], features [M,F], log-scales [M,6], source kf ids [M];
        offsets and statistics start at 0."""
        offsets = features.new_zeros(xyz.shape[0], self.k, 3)
        return self.rows.add({"xyz": xyz, "features": features, "offsets": offsets, "log_scales": log_scales, "kf_tag": kf_tag}, optimizer)

    def gaussian_positions(self) -> torch.Tensor:
        """[N,k,3] world positions of every anchor's k Gaussians (no gradient)."""
        scale = torch.exp(self.rows["log_scales"].detach()[:, :3])
        return self.xyz[:, None, :] + self.rows["offsets"].detach() * scale[:, None, :]

    def decode(self, view: View, embedding: torch.Tensor | None, cull: bool = True) -> tuple[Decoded, DecodeInfo]:
        """Decode the Gaussians of the anchors inside the view frustum (all anchors if not cull).

        embedding: [A] appearance embedding or None. The first layers of the three decoders
        share their input, so they run as one matrix product; the embedding's contribution to
        the colour decoder is the same for every anchor and enters as a bias.
        """
        if cull:
            visible = torch.nonzero(frustum_mask(self.xyz, view, self.frustum_margin)).squeeze(1)
        else:
            visible = torch.arange(len(self), device=self.xyz.device)
        # index_select, not t[idx]: its backward is index_add_, several times faster on the CPU
        # than the accumulating index_put_ of advanced indexing (the same sums)
        pick = torch.index_select
        xyz = pick(self.xyz, 0, visible)
        rel = xyz - view.center.to(xyz)
        dist = rel.norm(dim=-1, keepdim=True).clamp_min(1e-8)
        x = torch.cat([pick(self.rows["features"], 0, visible), rel / dist] + ([dist] if self.use_distance else []), -1)
        h_op, h_cov, h_col = self._hidden(x, embedding)
        opacity = torch.tanh(self.mlp_opacity[2](h_op))  # [V,k]
        keep = torch.nonzero(opacity.detach().reshape(-1) > 0).squeeze(1)  # rendered slots
        lin_cov, lin_col = self.mlp_cov[2], self.mlp_color[2]
        decoded = Decoded(*self.assemble(xyz, pick(self.rows["log_scales"], 0, visible), pick(self.rows["offsets"], 0, visible),
                                         h_cov, h_col, opacity, keep, lin_cov.weight, lin_cov.bias, lin_col.weight, lin_col.bias))
        return decoded, DecodeInfo(visible, keep, opacity.detach())

    def compile_assembly(self) -> None:
        """Replace `assemble` with its torch.compile form (dynamic shapes: one compilation serves
        every visible-anchor count): the gathers and activations fuse into a few kernels forward
        and backward, fewer launches per step on a GPU. Values agree with the eager form to float
        rounding."""
        self.assemble = torch.compile(assemble, dynamic=True)

    def _hidden(self, x: torch.Tensor, embedding: torch.Tensor | None) -> tuple[torch.Tensor, ...]:
        """ReLU hidden layers [V,hidden] of the opacity, covariance and colour decoders."""
        n_in = x.shape[1]
        first = (self.mlp_opacity[0], self.mlp_cov[0], self.mlp_color[0])
        weight = torch.cat([first[0].weight, first[1].weight, first[2].weight[:, :n_in]], 0)
        bias_col = first[2].bias
        if self.appearance_dim and embedding is not None:
            bias_col = bias_col + first[2].weight[:, n_in:] @ embedding.to(x)
        bias = torch.cat([first[0].bias, first[1].bias, bias_col])
        return torch.relu(torch.addmm(bias, x, weight.T)).split(first[0].out_features, dim=1)
