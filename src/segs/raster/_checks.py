"""Input validation for :func:`segs.raster.rasterize`.

Every check raises :class:`ValueError` naming the argument, the shape (dtype, device) it got and
the one it expected, so that a caller can fix the call from the message alone.
"""
from __future__ import annotations

import math

import torch

from ._projection import EPS2D

FLOAT_DTYPES = (torch.float32, torch.float64)


def _describe(t: torch.Tensor) -> str:
    return f"shape {list(t.shape)} {str(t.dtype).replace('torch.', '')} on {t.device}"


def _check_tensor(name: str, t, shape: tuple, n_name: str = "N") -> torch.Tensor:
    """Check one tensor argument; ``shape`` uses -1 for the Gaussian count N."""
    expected = "[" + ", ".join(n_name if s == -1 else str(s) for s in shape) + "]"
    if not isinstance(t, torch.Tensor):
        raise ValueError(f"{name}: expected a tensor of shape {expected}, got {type(t).__name__}")
    if t.dtype not in FLOAT_DTYPES:
        raise ValueError(
            f"{name}: expected float32 or float64 of shape {expected}, got {_describe(t)}"
        )
    ok = t.dim() == len(shape) and all(s == -1 or s == d for s, d in zip(shape, t.shape))
    if not ok:
        raise ValueError(f"{name}: expected shape {expected}, got {_describe(t)}")
    return t


def _check_finite(tensors: dict[str, torch.Tensor], K: torch.Tensor) -> tuple[float, float]:
    """Raise for the first tensor holding a nan / inf; returns K's focal lengths (fx, fy).

    One float64 sum per tensor (cannot overflow for float32 input: finite iff every entry is),
    read back with K's diagonal in ONE device-to-host copy: on a GPU each read is a sync.
    """
    names = [n for n, t in tensors.items() if t.numel()]
    sums = [tensors[n].detach().sum(dtype=torch.float64) for n in names]
    read = torch.stack(sums + [K[0, 0].detach().double(), K[1, 1].detach().double()]).tolist()
    for name, total in zip(names, read):
        if not math.isfinite(total):
            t = tensors[name]
            bad = int((~torch.isfinite(t)).sum())
            raise ValueError(f"{name}: {bad} non-finite value(s) (nan/inf) in {_describe(t)}")
    return read[-2], read[-1]


def check_inputs(
    means, quats, scales, opacities, colors, viewmat, K, width, height, background, near, far, check_values=True, eps2d=EPS2D
) -> None:
    """Validate the arguments of :func:`segs.raster.rasterize` (see there for shapes); the
    tensors' values (finite, K's focal lengths) only with check_values.

    Raises ValueError naming the offending argument, its shape and the expected one.
    """
    _check_tensor("means", means, (-1, 3))
    n = means.shape[0]
    tensors = {
        "means": means,
        "quats": _check_tensor("quats", quats, (-1, 4)),
        "scales": _check_tensor("scales", scales, (-1, 3)),
        "opacities": _check_tensor("opacities", opacities, (-1,)),
        "colors": _check_tensor("colors", colors, (-1, 3)),
        "viewmat": _check_tensor("viewmat", viewmat, (4, 4)),
        "K": _check_tensor("K", K, (3, 3)),
    }
    if background is not None:
        tensors["background"] = _check_tensor("background", background, (3,))
    for name in ("quats", "scales", "opacities", "colors"):
        if tensors[name].shape[0] != n:
            raise ValueError(
                f"{name}: expected N={n} rows like means ({list(means.shape)}), "
                f"got {_describe(tensors[name])}"
            )
    for name, t in tensors.items():
        if t.device != means.device:
            raise ValueError(f"{name}: expected device {means.device} like means, got {_describe(t)}")
        if t.dtype != means.dtype:
            raise ValueError(f"{name}: expected dtype {means.dtype} like means, got {_describe(t)}")
    _check_camera(_check_finite(tensors, K) if check_values else None, width, height, near, far)
    if not isinstance(eps2d, (int, float)) or not (math.isfinite(eps2d) and eps2d >= 0):
        raise ValueError(f"eps2d: expected a finite float >= 0 (pixels^2), got {eps2d!r}")


def _check_camera(focal: tuple[float, float] | None, width, height, near, far) -> None:
    for name, v in (("width", width), ("height", height)):
        if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
            raise ValueError(f"{name}: expected a positive int, got {v!r}")
    if focal is not None and min(focal) <= 0:
        raise ValueError(f"K: expected positive focal lengths K[0,0], K[1,1], got {focal[0]}, {focal[1]}")
    for name, v in (("near", near), ("far", far)):
        if not isinstance(v, (int, float)) or not math.isfinite(v):
            raise ValueError(f"{name}: expected a finite float, got {v!r}")
    if not 0 < near < far:
        raise ValueError(f"near, far: expected 0 < near < far, got near={near}, far={far}")
