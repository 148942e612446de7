"""OrbFrontend checkpoints written before segs.slam's stages became subpackages still load
(converted to segs.state.v3): their blob pickles classes under the former module names
(segs.slam.map, segs.slam.tracking, ...)."""
from __future__ import annotations

import contextlib
import importlib
import inspect
import pickle
import sys
import types

import numpy as np
import pytest

from conftest import orb_v2_state
from segs.config import slam_frontend
from segs.data.synthetic import SyntheticSequence
from segs.pipeline.sources import run_sequence
from segs.slam.orb_state import MOVED_MODULES


@contextlib.contextmanager
def _former_module_names(monkeypatch):
    """Inside: every class of a moved module pickles as the code before the move did (its
    __module__ the former name, found there by pickle's check); restored on leaving."""
    with monkeypatch.context() as m:
        for old, new in MOVED_MODULES.items():
            module = importlib.import_module(new)
            if old not in sys.modules:
                m.setitem(sys.modules, old, types.ModuleType(old))
            for name, cls in vars(module).items():
                if inspect.isclass(cls) and cls.__module__ == new:
                    m.setattr(cls, "__module__", old)
                    m.setattr(sys.modules[old], name, cls, raising=False)
        yield


def test_a_checkpoint_naming_the_former_modules_loads_and_tracks_on(monkeypatch):
    seq = SyntheticSequence(sensor="rgbd", n_frames=12, width=320, height=240, trajectory="orbit", speed=0.3, seed=0)
    fe = slam_frontend(seq.camera, "rgbd")
    run_sequence(fe, seq, frames=range(6))
    with _former_module_names(monkeypatch):
        state = orb_v2_state(fe)
    blob = state["blob"]
    # the stream names the former modules, never the new ones
    for old in ("segs.slam.map", "segs.slam.vocabulary", "segs.slam.features", "segs.slam.frame_poses", "segs.slam.tracking"):
        assert old.encode() in blob, old
    assert not any(new.encode() in blob for new in MOVED_MODULES.values())
    with pytest.raises((ModuleNotFoundError, AttributeError)):
        pickle.loads(blob)  # what the plain unpickler makes of it

    old_fe = slam_frontend(seq.camera, "rgbd")
    old_fe.load_state_dict(state)
    assert type(old_fe.map).__module__ == "segs.slam.map.map"
    assert old_fe.keyframe_frames() == fe.keyframe_frames()
    run_sequence(fe, seq, frames=range(6, 12))
    run_sequence(old_fe, seq, frames=range(6, 12))
    want, got = fe.trajectory(), old_fe.trajectory()
    assert got.keys() == want.keys() == set(range(12))
    assert all(np.array_equal(got[i], want[i]) for i in want)


def test_every_former_module_name_points_at_a_module():
    """The table is current: each target is a module, and a former name that is now a package
    defines no class in its __init__ (the table would hide it from a blob)."""
    for old, new in MOVED_MODULES.items():
        assert not hasattr(importlib.import_module(new), "__path__"), new
        try:
            package = importlib.import_module(old)
        except ModuleNotFoundError:
            continue
        assert hasattr(package, "__path__"), f"{old} is still a module"
        assert not any(inspect.isclass(c) and c.__module__ == old for c in vars(package).values()), old
