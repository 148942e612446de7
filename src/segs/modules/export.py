"""Standard 3D-GS PLY export (the attribute layout read by common 3DGS viewers)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement

SH_C0 = 0.28209479177387814


def rgb_to_sh_dc(rgb: torch.Tensor) -> torch.Tensor:
    """Colour [N,3] in [0,1] -> degree-0 SH coefficient [N,3]."""
    return (rgb - 0.5) / SH_C0


def write_gaussian_ply(
    path: str | Path,
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    sh_dc: torch.Tensor,
    sh_rest: torch.Tensor | None = None,
) -> int:
    """Write Gaussians as 3D-GS PLY: x y z nx ny nz f_dc_* f_rest_* opacity scale_* rot_*.

    means [N,3]; quats [N,4] wxyz; scales [N,3] linear (stored as log); opacities [N] in (0,1)
    (stored as logit); sh_dc [N,3]; sh_rest [N,K,3] or None (stored channel-major as 3D-GS does).
    The file is written to a temporary name and renamed, so a partial file never looks finished.
    """
    n = means.shape[0]
    cols = {
        "xyz": means.detach().cpu().float(),
        "normals": torch.zeros(n, 3),
        "f_dc": sh_dc.detach().cpu().float(),
    }
    rest = sh_rest.detach().cpu().float().transpose(1, 2).reshape(n, -1) if sh_rest is not None else torch.zeros(n, 0)
    op = opacities.detach().cpu().float().clamp(1e-6, 1 - 1e-6)
    fields = (
        [("x", cols["xyz"][:, 0]), ("y", cols["xyz"][:, 1]), ("z", cols["xyz"][:, 2])]
        + [(f"n{a}", cols["normals"][:, i]) for i, a in enumerate("xyz")]
        + [(f"f_dc_{i}", cols["f_dc"][:, i]) for i in range(3)]
        + [(f"f_rest_{i}", rest[:, i]) for i in range(rest.shape[1])]
        + [("opacity", torch.log(op / (1 - op)))]
        + [(f"scale_{i}", torch.log(scales.detach().cpu().float().clamp_min(1e-12))[:, i]) for i in range(3)]
        + [(f"rot_{i}", quats.detach().cpu().float()[:, i]) for i in range(4)]
    )
    arr = np.empty(n, dtype=[(name, "f4") for name, _ in fields])
    for name, col in fields:
        arr[name] = col.numpy()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    PlyData([PlyElement.describe(arr, "vertex")]).write(str(tmp))
    tmp.replace(path)
    return n
