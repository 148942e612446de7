"""Shared fixtures: composed configs for tiny CPU runs, the shared real data; the `slow` mark.

`pytest` runs the fast suite (pyproject.toml: -m "not slow"); `pytest -m slow` runs the rest:
long end-to-end runs (marked where they are defined) and every test that reads the shared real
data in ../shared/data (marked here, by the fixture that finds it). CI runs both."""
from __future__ import annotations

import importlib.util
import os
from pathlib import Path

import pytest

from segs import process_settings
from segs.config import compose


def pytest_configure(config):
    """The process settings of segs's programs, before a test module loads torch."""
    process_settings.apply()


TINY = [
    "+experiment=synthetic",
    "slam=known_poses",
    "data.n_frames=14",
    "data.width=96",
    "data.height=72",
    "trainer.max_steps=40",
    "logger=none",
    "callbacks.slam_bridge.progress=false",
    "callbacks.slam_bridge.min_initial_keyframes=3",
    "~callbacks.progress_bar",
    "callbacks.image_logger.every_n_steps=0",
    "slam.keyframe_every=3",
    "slam.n_features=300",
    "eval.holdout_every=3",
    "eval.save_renders=2",
    "eval.ply_fit_steps=20",
    "trainer.enable_progress_bar=false",
]


@pytest.fixture
def tiny_cfg(tmp_path):
    """A factory: compose the tiny synthetic run (known poses) with extra overrides."""

    def make(*overrides: str, out=None):
        return compose(TINY + list(overrides), output_dir=str(out or tmp_path / "run"))

    return make


# the shared real data (non-commercial licences, never in the repository): ../shared/data beside
# the checkout, or the folder named by SEGS_SHARED_DATA (a worktree elsewhere)
SHARED_DATA = Path(os.environ.get("SEGS_SHARED_DATA") or Path(__file__).resolve().parents[1].parent / "shared" / "data")
SEVEN_SCENES = SHARED_DATA / "7scenes_redkitchen_0000_0599"
KITTI = SHARED_DATA / "kitti_odometry_51"


@pytest.fixture(scope="session")
def seven_scenes_root():
    """The shared 600 real 7-Scenes redkitchen frames (../shared/data; non-commercial licence, not
    in the repository); tests using it are skipped where the folder is absent."""
    if not (SEVEN_SCENES / "seq").is_dir():
        pytest.skip(f"7-Scenes frames not found at {SEVEN_SCENES} (shared data, not in the repository)")
    return SEVEN_SCENES


@pytest.fixture(scope="session")
def kitti_root():
    """The shared 51 real KITTI odometry frames (left camera, ground truth; ../shared/data,
    CC BY-NC-SA 3.0, not in the repository); tests using it are skipped where it is absent."""
    if not (KITTI / "image_0").is_dir():
        pytest.skip(f"KITTI frames not found at {KITTI} (shared data, not in the repository)")
    return KITTI


# fixtures that find real data outside the repository (../shared/data): their tests are slow
SHARED_DATA_FIXTURES = {"seven_scenes_root", "kitti_root"}


def pytest_collection_modifyitems(config, items):
    for item in items:
        if SHARED_DATA_FIXTURES & set(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.slow)


def orb_v2_state(fe) -> dict:
    """The "segs.orb.v2" state of an OrbFrontend, as checkpoints before segs.state.v3 held it: the
    map, keyframe database, outbox and the components' state fields pickled in one blob."""
    import pickle

    data = {"map": fe.map, "kfdb": fe.kfdb, "outbox": fe.outbox, "tracker": fe.tracker.state_fields(),
            "mapper": fe.local_mapping.state_fields(), "loop": fe.loop.state_fields()}  # fmt: skip
    lock, fe.map.lock = fe.map.lock, None
    try:
        blob = pickle.dumps(data, protocol=pickle.HIGHEST_PROTOCOL)
    finally:
        fe.map.lock = lock
    return {"format": "segs.orb.v2", "blob": blob}


def se3(rv, t):
    """[4,4] pose from a rotation vector [3] (radians, cv2.Rodrigues) and a translation [3]."""
    import cv2
    import numpy as np

    T = np.eye(4)
    T[:3, :3], T[:3, 3] = cv2.Rodrigues(np.asarray(rv, np.float64).reshape(3, 1))[0], t
    return T


def project(K, T, P):
    """Pinhole projection of world points P [N,3] by the world-to-camera T [4,4] with intrinsics
    K [3,3]: (pixels [N,2], depths [N])."""
    import numpy as np

    pc = P @ T[:3, :3].T + T[:3, 3]
    return np.stack([K[0, 0] * pc[:, 0] / pc[:, 2] + K[0, 2], K[1, 1] * pc[:, 1] / pc[:, 2] + K[1, 2]], 1), pc[:, 2]


def load_bench(name: str, module: str | None = None):
    """A bench/ script as a module (bench/ is not a package): load_bench("mono_forward")."""
    path = Path(__file__).resolve().parents[1] / "bench" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(module or f"{name.lstrip('_')}_bench", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def instances_in(value, where: str = "state") -> list[str]:
    """Paths of the values of a checkpoint state that are neither numbers, strings, arrays nor
    plain containers (segs.state.v3 holds no class instance)."""
    import numpy as np
    import torch

    if isinstance(value, dict):
        return [p for k, v in value.items() for p in instances_in(v, f"{where}.{k}")]
    if isinstance(value, (list, tuple)):
        return [p for i, v in enumerate(value) for p in instances_in(v, f"{where}[{i}]")]
    if isinstance(value, np.ndarray) and value.dtype == object:
        return [f"{where}: object array"]
    plain = (bool, int, float, str, type(None), np.ndarray, torch.Tensor, np.bool_, np.integer, np.floating)
    return [] if isinstance(value, plain) else [f"{where}: {type(value).__name__}"]
