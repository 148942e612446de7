"""How a run was made: the record written as `provenance` into metrics.json and tracking.json.

A result file alone must answer "what produced this number": the frontend and sensor, the raster
backend that actually rendered, the device and threads, the library versions, the seed, the
command-line overrides, the package version and git commit (with a dirty flag) and the machine.
Nothing here imports torch: `segs.track` runs without it (torch's version is read from the
installed package's metadata, its thread count only when torch is already loaded).
"""
from __future__ import annotations

import functools
import os
import platform
import subprocess
import sys
from importlib import metadata
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from segs import process_settings

# the folder holding src/ when the package runs from a checkout (pip install -e .)
_CHECKOUT = Path(__file__).resolve().parents[2]
# slam._target_ -> the frontend's short name (conf/slam/<name>.yaml)
FRONTENDS = {"segs.slam.orb.OrbFrontend": "orb", "segs.slam.known_poses.KnownPosesFrontend": "known_poses"}


def _version(dist: str) -> str | None:
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return None


@functools.lru_cache(maxsize=1)
def git_state(root: Path = _CHECKOUT) -> dict:
    """{"commit": sha or None, "dirty": bool or None}: None where the package is not run from a
    git checkout (an installed wheel) or git is missing. dirty: tracked files differ from HEAD."""
    if not (root / ".git").exists():
        return {"commit": None, "dirty": None}
    try:
        run = functools.partial(subprocess.run, cwd=root, capture_output=True, text=True, timeout=10, check=True)
        commit = run(["git", "rev-parse", "HEAD"]).stdout.strip()
        dirty = bool(run(["git", "status", "--porcelain", "--untracked-files=no"]).stdout.strip())
    except (OSError, subprocess.SubprocessError):
        return {"commit": None, "dirty": None}
    return {"commit": commit, "dirty": dirty}


@functools.lru_cache(maxsize=1)
def machine() -> dict:
    """CPU model, logical cores (and those this process may use), OS and Python."""
    model = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return {"cpu": model, "cores": os.cpu_count(), "cores_usable": usable, "os": platform.platform(terse=True),
            "python": platform.python_version()}  # fmt: skip


def command_overrides() -> list[str] | None:
    """The overrides of the command line (Hydra's task overrides), None outside a Hydra run."""
    try:
        from hydra.core.hydra_config import HydraConfig

        return list(HydraConfig.get().overrides.task)
    except (ValueError, AttributeError):  # no Hydra config set (a script calling run() itself)
        return None


def frontend_name(cfg: DictConfig) -> str:
    """conf/slam group name of the configured frontend (its class path when unknown)."""
    target = str(OmegaConf.select(cfg, "slam._target_", default="?"))
    return FRONTENDS.get(target, target)


def threads() -> dict:
    """Thread settings that shape speed: torch's intra-op threads (when torch is loaded), the OpenMP
    environment, OpenCV's threads (when OpenCV is loaded)."""
    torch = sys.modules.get("torch")
    cv2 = sys.modules.get("cv2")
    return {
        "torch": torch.get_num_threads() if torch is not None else None,
        "opencv": cv2.getNumThreads() if cv2 is not None else None,
        "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS"),
        "OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY"),
        "GOMP_SPINCOUNT": os.environ.get("GOMP_SPINCOUNT"),
    }


def provenance(cfg: DictConfig, sensor: str, raster_backend: str | None = None, device: str | None = None) -> dict:
    """The record of how this run was made (module doc). sensor: the sequence's (mono / stereo /
    rgbd); raster_backend: the backend that rendered (None: nothing was rendered, e.g. segs.track);
    device: the mapper's device (None: no mapper)."""
    git = git_state()
    return {
        "frontend": frontend_name(cfg),
        "slam_mode": OmegaConf.select(cfg, "slam_mode", default="interleaved"),
        "sensor": sensor,
        "raster_backend": raster_backend,
        "device": device,
        "threads": threads(),
        "malloc": process_settings.malloc_setting(),  # "kept": the program applied segs.process_settings
        "seed": OmegaConf.select(cfg, "seed", default=None),
        "overrides": command_overrides(),
        "segs_version": _version("segs"),
        "git_commit": git["commit"],
        "git_dirty": git["dirty"],
        "versions": {name: _version(name) for name in ("torch", "gsplat", "lightning", "opencv-contrib-python-headless", "gtsam",
                                                       "numpy")},  # fmt: skip
        "machine": machine(),
    }
