"""Build the C++ CPU kernels once (torch.utils.cpp_extension + ninja) and load them.

The build lives in a per-user cache directory, one folder per key: a hash of the sources, the
compiler flags, the torch and Python versions and this CPU's instruction-set flags (the code is
compiled with ``-march=native``, so a build is only reused on a CPU with the same flags). A
cached build is imported directly (no compiler, no ninja: well under a second).

Environment:
    SEGS_RASTER_CACHE_DIR   build cache (default: $XDG_CACHE_HOME/segs/raster or ~/.cache/...)
    SEGS_RASTER_NO_CPU=1    pretend the CPU backend cannot be built (tests, debugging)
    CXX                     C++ compiler (default: c++)
"""
from __future__ import annotations

import hashlib
import importlib.util
import os
import platform
import shutil
import sys
import threading
from pathlib import Path
from types import ModuleType

CSRC = Path(__file__).parent / "csrc"
SOURCES = ("bindings.cpp", "projection.cpp", "binning.cpp", "forward.cpp", "backward.cpp", "ssim.cpp")
HEADERS = ("raster.h", "projection.h", "simd.h", "pool.h", "ssim.h")
_lock = threading.Lock()
_module: ModuleType | None = None
_error: str | None = None


class BuildError(RuntimeError):
    """The CPU kernels cannot be compiled or loaded here; the message says why."""


def _cflags() -> list[str]:
    flags = ["-O3", "-fopenmp", "-ffp-contract=fast", "-fno-math-errno", "-fno-trapping-math",
             "-Wno-psabi"]
    if platform.machine() in ("x86_64", "AMD64"):
        flags.append("-march=native")
    return flags


def _cpu_signature() -> str:
    """Model and instruction-set flags of this CPU (what -march=native depends on)."""
    keys, found = ("model name", "flags", "Features"), {}
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key = line.split(":", 1)[0].strip()
            if key in keys:
                found.setdefault(key, line)
    except OSError:
        pass
    return "\n".join(found.values()) or platform.processor() or platform.machine()


def cache_dir() -> Path:
    """Root of the per-user build cache."""
    if os.environ.get("SEGS_RASTER_CACHE_DIR"):
        return Path(os.environ["SEGS_RASTER_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "segs" / "raster"


def build_name() -> str:
    """Extension name = ``segs_raster_cpu_<hash of everything the binary depends on>``."""
    import torch

    h = hashlib.sha256()
    for f in SOURCES + HEADERS:
        h.update(f.encode() + (CSRC / f).read_bytes())
    parts = [" ".join(_cflags()), torch.__version__, sys.version, platform.machine(), _cpu_signature()]
    h.update("\n".join(parts).encode())
    return f"segs_raster_cpu_{h.hexdigest()[:16]}"


def _import_built(name: str, build_dir: Path) -> ModuleType | None:
    so = build_dir / f"{name}.so"
    if not so.exists() or (build_dir / "lock").exists():
        return None
    spec = importlib.util.spec_from_file_location(name, so)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _compile(name: str, build_dir: Path) -> ModuleType:
    from torch.utils import cpp_extension

    cxx = os.environ.get("CXX", "c++")
    if shutil.which(cxx) is None:
        raise BuildError(f"no C++ compiler: '{cxx}' not found on PATH (install g++ or set CXX)")
    if not cpp_extension.is_ninja_available():
        raise BuildError("ninja is not installed (pip install ninja)")
    build_dir.mkdir(parents=True, exist_ok=True)
    try:
        return cpp_extension.load(
            name, [str(CSRC / f) for f in SOURCES], extra_cflags=_cflags(),
            extra_ldflags=["-fopenmp"], build_directory=str(build_dir), verbose=False,
        )
    except Exception as exc:  # compiler errors arrive as RuntimeError with the ninja log
        lines = [ln for ln in str(exc).splitlines() if "error" in ln.lower()][:5]
        detail = "; ".join(lines) or str(exc).splitlines()[0]
        raise BuildError(f"building the C++ kernels failed in {build_dir}: {detail}") from exc


def load_extension() -> ModuleType:
    """The compiled kernels, building them on first use; raises BuildError saying why not."""
    global _module, _error
    if os.environ.get("SEGS_RASTER_NO_CPU") == "1":
        raise BuildError("disabled by SEGS_RASTER_NO_CPU=1")
    if _module is not None:
        return _module
    with _lock:
        if _module is not None:
            return _module
        if _error is not None:
            raise BuildError(_error)
        name = build_name()
        build_dir = cache_dir() / name
        try:
            _module = _import_built(name, build_dir) or _compile(name, build_dir)
        except BuildError as exc:
            _error = str(exc)
            raise
        except Exception as exc:  # e.g. a corrupt cached .so
            _error = f"loading the C++ kernels from {build_dir} failed: {exc}"
            raise BuildError(_error) from exc
        return _module
