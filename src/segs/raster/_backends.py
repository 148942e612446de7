"""Backend registry: which backends can run here, and which one ``"auto"`` picks."""
from __future__ import annotations

import warnings

import torch

from . import _cuda_backend
from ._build import BuildError, load_extension

BACKENDS = ("auto", "cuda", "cpu", "torch")
_warned: set[str] = set()


class BackendUnavailableError(RuntimeError):
    """A backend was named that cannot run here; the message says why and what can."""


def _cpu_reason() -> str | None:
    try:
        load_extension()
    except BuildError as exc:
        return str(exc)
    return None


def unavailable_reasons() -> dict[str, str | None]:
    """Backend name -> None if it can run on this machine, else the reason it cannot."""
    return {"cuda": _cuda_backend.unavailable_reason(), "cpu": _cpu_reason(), "torch": None}


def available_backends() -> list[str]:
    """Names of the backends usable on this machine, fastest first (builds the CPU kernels)."""
    return [name for name, why in unavailable_reasons().items() if why is None]


def _device_reason(name: str, device: torch.device) -> str | None:
    if name == "cuda" and device.type != "cuda":
        return f"the cuda backend renders CUDA tensors, got tensors on {device}"
    if name == "cpu" and device.type != "cpu":
        return f"the cpu backend renders CPU tensors, got tensors on {device}"
    return None


def _warn_once(key: str, message: str) -> None:
    if key not in _warned:
        _warned.add(key)
        warnings.warn(message, RuntimeWarning, stacklevel=4)


def resolve(backend: str, device: torch.device) -> str:
    """The concrete backend for ``backend`` and tensors on ``device``.

    "auto": cuda (gsplat) for CUDA tensors, cpu (C++) for CPU tensors, torch when that one
    cannot run (warning once). A named backend that cannot run raises
    BackendUnavailableError with the reason and the backends that can.
    """
    if backend not in BACKENDS:
        raise ValueError(f"backend: expected one of {list(BACKENDS)}, got {backend!r}")
    if backend == "torch":
        return "torch"
    if backend == "auto":
        name = "cuda" if device.type == "cuda" else "cpu"
        why = _cuda_backend.unavailable_reason() if name == "cuda" else _cpu_reason()
        if why is not None:
            _warn_once(name, f"segs.raster: backend {name!r} unavailable ({why}); using 'torch'")
            return "torch"
        return name
    why = _device_reason(backend, device) or unavailable_reasons()[backend]
    if why is not None:
        ok = [n for n, r in unavailable_reasons().items() if r is None and not _device_reason(n, device)]
        raise BackendUnavailableError(
            f"backend {backend!r} is unavailable: {why}. Available for tensors on {device}: {ok}"
        )
    return backend
