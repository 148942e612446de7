"""The frontend's C++ kernels (src/segs/slam/native/csrc/match.cpp, map.cpp, pose.cpp), built on first use.

The projection search, the motion-only LM and the map bookkeeping loops (see the .cpp files) give
the results of the numpy / Python code they replace; tests/test_slam_units.py compares the two.
Without a compiler, or with ``SEGS_SLAM_NO_CPU=1``, `kernels()` returns None (one warning) and the
numpy / Python code runs: same results, slower.

The build needs no torch (SLAM processes stay free of it): one call of the C++ compiler with
pybind11's headers, cached per user under ``$SEGS_SLAM_CACHE_DIR`` (default
``$XDG_CACHE_HOME/segs/slam`` or ``~/.cache/segs/slam``) by a hash of the sources, the flags, the
Python and pybind11 versions and this CPU's instruction-set flags (``-march=native``).
Floating-point contraction is off, so that sums and products round as numpy's do.
"""
from __future__ import annotations

import hashlib
import importlib.util
import os
import platform
import shutil
import subprocess
import sys
import sysconfig
import tempfile
import threading
import warnings
from pathlib import Path
from types import ModuleType

CSRC = Path(__file__).parent / "csrc"
SOURCES = ("match.cpp", "map.cpp", "pose.cpp")
HEADERS = ("common.h",)
FLAGS = ("-O3", "-std=c++17", "-shared", "-fPIC", "-ffp-contract=off", "-fvisibility=hidden")
_lock = threading.Lock()
_state: dict[str, object] = {}  # "module" or "error", once per process


def _cpu_flags() -> str:
    """This CPU's model and instruction-set flags (what -march=native compiles for)."""
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        return platform.machine()
    wanted = [ln for ln in lines if ln.split(":")[0].strip() in ("model name", "flags", "Features")]
    return "\n".join(dict.fromkeys(wanted)) or platform.machine()


def _flags() -> list[str]:
    native = ["-march=native"] if platform.machine() in ("x86_64", "AMD64") else []
    return [*FLAGS, *native]


def _name() -> str:
    import pybind11

    h = hashlib.sha256()
    for f in SOURCES + HEADERS:
        h.update(f.encode() + (CSRC / f).read_bytes())
    h.update("\n".join([" ".join(_flags()), sys.version, pybind11.__version__, _cpu_flags()]).encode())
    return f"segs_slam_native_{h.hexdigest()[:16]}"


def _cache() -> Path:
    if os.environ.get("SEGS_SLAM_CACHE_DIR"):
        return Path(os.environ["SEGS_SLAM_CACHE_DIR"])
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "segs" / "slam"


def _compile(name: str, target: Path) -> None:
    """One compiler call into a temporary file, renamed into place (concurrent builds are safe)."""
    try:
        import pybind11
    except ImportError as exc:
        raise RuntimeError("pybind11 is not installed (pip install pybind11)") from exc
    cxx = os.environ.get("CXX", "c++")
    if shutil.which(cxx) is None:
        raise RuntimeError(f"no C++ compiler: '{cxx}' not found on PATH")
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(suffix=target.suffix, dir=target.parent)
    os.close(fd)
    cmd = [cxx, *_flags(), f"-DSEGS_EXTENSION_NAME={name}", f"-I{pybind11.get_include()}",
           f"-I{sysconfig.get_paths()['include']}", *[str(CSRC / f) for f in SOURCES], "-o", tmp]
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode != 0:
        os.unlink(tmp)
        errors = [ln for ln in res.stderr.splitlines() if "error" in ln.lower()][:3]
        raise RuntimeError(f"compiling {', '.join(SOURCES)} failed: {'; '.join(errors) or res.stderr[-300:]}")
    os.replace(tmp, target)


def _load() -> ModuleType:
    name = _name()
    target = _cache() / f"{name}{sysconfig.get_config_var('EXT_SUFFIX') or '.so'}"
    if not target.exists():
        _compile(name, target)
    spec = importlib.util.spec_from_file_location(name, target)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def kernels() -> ModuleType | None:
    """The compiled module, or None (one warning per process saying why) where it cannot be built."""
    if "module" in _state:
        return _state["module"]  # type: ignore[return-value]
    if os.environ.get("SEGS_SLAM_NO_CPU") == "1":
        return None
    with _lock:
        if "module" not in _state and "error" not in _state:
            try:
                _state["module"] = _load()
            except Exception as exc:  # no compiler, no pybind11, a broken cached file
                _state["error"] = str(exc)
                warnings.warn(f"segs.slam: C++ kernels unavailable ({exc}); using numpy", stacklevel=2)
    return _state.get("module")  # type: ignore[return-value]
