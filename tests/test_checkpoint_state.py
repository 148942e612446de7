"""Checkpoint state (format segs.state.v3): plain arrays, numbers and containers, no class
instance; an ORB frontend saved mid-sequence and resumed tracks exactly as the uninterrupted one;
the earlier pickled formats (segs.orb.v2, the bridge's before v3) are converted when loaded."""
from __future__ import annotations

import io

import numpy as np
import pytest
import torch

from conftest import instances_in, orb_v2_state
from segs.config import slam_frontend
from segs.data.synthetic import SyntheticSequence
from segs.errors import ConfigError
from segs.pipeline.legacy import bridge_state
from segs.pipeline.sources import InterleavedSource, run_sequence
from segs.slam import orb_state
from segs.slam.base import STATE_FORMAT
from segs.slam.map.map import KeyFrame


def _sequence(sensor: str, n: int = 16) -> SyntheticSequence:
    return SyntheticSequence(sensor=sensor, n_frames=n, width=320, height=240, trajectory="orbit", speed=0.3, seed=0)


def _track(fe, seq, frames) -> None:
    """The frames tracked and polled as a run does before its end (no finish(), which flushes
    local mapping's recent points: a run saved mid-sequence has not finished)."""
    with InterleavedSource(fe, seq, frames) as source:
        while not source.exhausted():
            source.track(1)


def _reloaded(state: dict) -> dict:
    """The state written and read back as a checkpoint file is."""
    buf = io.BytesIO()
    torch.save(state, buf)
    buf.seek(0)
    return torch.load(buf, weights_only=False)


@pytest.mark.parametrize("sensor", ["rgbd", "mono"])
def test_an_orb_frontend_resumed_mid_sequence_tracks_as_the_uninterrupted_one(sensor):
    seq = _sequence(sensor)
    whole = slam_frontend(seq.camera, sensor)
    run_sequence(whole, seq)
    first = slam_frontend(seq.camera, sensor)
    _track(first, seq, range(8))
    state = first.state_dict()
    assert state["format"] == STATE_FORMAT and not instances_in(state)
    resumed = slam_frontend(seq.camera, sensor)
    resumed.load_state_dict(_reloaded(state))
    run_sequence(resumed, seq, frames=range(8, len(seq)))
    want, got = whole.trajectory(), resumed.trajectory()
    assert got.keys() == want.keys() and all(np.array_equal(got[i], want[i]) for i in want)
    assert resumed.keyframe_frames() == whole.keyframe_frames() and resumed.lost_frames() == whole.lost_frames()
    n = whole.map.n
    assert resumed.map.n == n and np.array_equal(resumed.map.pos[:n], whole.map.pos[:n])
    assert resumed.map.obs == whole.map.obs and resumed.kfdb.index == whole.kfdb.index


def test_the_state_covers_every_field_of_the_frontends_records():
    """A field added to KeyFrame or to a component's state fields must be encoded too."""
    seq = _sequence("rgbd", 8)
    fe = slam_frontend(seq.camera, "rgbd")
    run_sequence(fe, seq)
    kf = next(iter(fe.map.kfs.values()))
    assert set(vars(kf)) == set(orb_state.KEYFRAME_FIELDS) and isinstance(kf, KeyFrame)
    assert set(fe.tracker._STATE) == set(orb_state.TRACKER_FIELDS)
    assert set(fe.local_mapping._STATE) == {"recent", "ba_times"} and set(fe.loop._STATE) == {"groups", "last_loop_kf", "loops"}


def test_a_v2_checkpoint_is_converted_and_tracks_on():
    seq = _sequence("rgbd", 12)
    fe = slam_frontend(seq.camera, "rgbd")
    _track(fe, seq, range(6))
    old = slam_frontend(seq.camera, "rgbd")
    old.load_state_dict(orb_v2_state(fe))
    assert not instances_in(old.state_dict())  # saved again: v3
    run_sequence(fe, seq, frames=range(6, 12))
    run_sequence(old, seq, frames=range(6, 12))
    want, got = fe.trajectory(), old.trajectory()
    assert got.keys() == want.keys() and all(np.array_equal(got[i], want[i]) for i in want)


def test_a_state_of_another_kind_or_format_is_one_line():
    seq = _sequence("rgbd", 4)
    fe = slam_frontend(seq.camera, "rgbd")
    for bad in ({"format": STATE_FORMAT, "kind": "known_poses"}, {"format": "segs.orb.v9"}):
        with pytest.raises(ConfigError) as err:
            fe.load_state_dict(bad)
        assert len(str(err.value).splitlines()) == 1
    with pytest.raises(ConfigError, match="format 'segs.run.v9'"):
        bridge_state({"format": "segs.run.v9"})


def test_a_bridge_state_before_v3_is_converted():
    old = {"cursor": 7, "credit": 0.25, "frames_per_step": 0.5, "finished": False, "trained_frames": {0: 0, 2: 5},
           "held_out_keyframes": [1], "held_out_points": 12, "process_seconds": 1.5, "processed": 7,
           "frontend": {"poses": {}, "lost": [], "kf_frames": {}, "last_kf": None}}  # fmt: skip
    new = bridge_state(old)
    assert new["format"] == STATE_FORMAT and new["credit"] == 0.25 and not instances_in(new)
    run = new["run"]
    assert run["source"]["cursor"] == 7 and run["source"]["frames_done"] == 7 and run["held_out_points"] == 12
    assert run["keyframes"]["kf_id"].tolist() == [0, 1, 2] and run["keyframes"]["trained"].tolist() == [True, False, True]
    assert run["keyframes"]["frame_index"].tolist() == [0, -1, 5]


def test_the_segs_models_waiting_points_are_saved():
    """SEGS's points waiting for min_new_points are part of a checkpoint: a resumed model adds
    the same anchors as the uninterrupted one."""
    from segs.config import model_node
    from segs.modules.config import build_model, mapping_config, raster_config
    from segs.modules.gaussian_mapper import GaussianMapperModule

    mapping = mapping_config({"view_budget": 2, "min_scene_extent": 0.5, "adam_eps": 1e-15, "num_downscales": 0, "downscale_phase": 0.1,
                              "min_schedule_steps": 0, "render_filter": "trained", "render_filter_decay": 0.95, "compile": False})
    raster = raster_config({"backend": "torch", "near": 0.01, "far": 100.0, "background": [0, 0, 0]})
    make = lambda: GaussianMapperModule(build_model(model_node("segs", min_new_points=50)), mapping, raster, seed=0)  # noqa: E731
    torch.manual_seed(0)
    first, second, third = torch.rand(60, 3), torch.rand(30, 3), torch.rand(30, 3)
    kf = lambda n, k: torch.full((n,), k)  # noqa: E731
    whole, saved = make(), make()
    for m in (whole, saved):
        m.add_points(first, first, kf(60, 0))
        m.add_points(second, second, kf(30, 1))  # 30 < 50: waits
    checkpoint = {"state_dict": saved.state_dict()}
    saved.on_save_checkpoint(checkpoint)
    assert not instances_in(checkpoint["segs"]["model"]) and len(checkpoint["segs"]["model"]["pending_xyz"]) == 30
    resumed = make()
    resumed.on_load_checkpoint(checkpoint)
    resumed.load_state_dict(checkpoint["state_dict"])
    for m in (whole, resumed):
        m.add_points(third, third, kf(30, 2))  # 60 waiting: added now
    assert torch.equal(resumed.model.field.xyz, whole.model.field.xyz) and len(whole.model.field) > 0
