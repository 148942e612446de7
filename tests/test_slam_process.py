"""The frontend in its own process (slam_mode=process | live): same results as in-process,
checkpoints that resume without losing or repeating updates, live pacing that drops frames."""
from __future__ import annotations

import functools
import json
from pathlib import Path

import numpy as np
import pytest

from conftest import instances_in
from segs.config import compose, instantiate, make_sequence, make_source
from segs.errors import ConfigError, DataError
from segs.pipeline.process import LiveSource, ProcessSource
from segs.pipeline.readers import CameraFrames, next_live
from segs.pipeline.sources import run_sequence
from segs.slam.base import MapUpdate

BASE = ["+experiment=synthetic", "data.n_frames=16", "data.width=320", "data.height=240",
        "data.trajectory=orbit", "data.speed=0.2"]


def _setup(tmp_path, *extra):
    cfg = compose(BASE + list(extra), output_dir=str(tmp_path))
    seq = make_sequence(cfg.data)
    factory = functools.partial(instantiate(cfg.slam), camera=seq.camera, sensor=seq.sensor)
    return cfg, seq, factory


def _drain(fe: ProcessSource) -> MapUpdate:
    up = MapUpdate()
    while not fe.exhausted():
        up = up.merge(fe.track(timeout=0.2))
    return up


def test_process_mode_gives_the_in_process_trajectory_and_updates(tmp_path):
    _, seq, factory = _setup(tmp_path)
    ref_fe = factory()
    ref = run_sequence(ref_fe, seq)
    fe = ProcessSource(factory, seq)
    try:
        up = _drain(fe)
        assert fe.frames_done == len(seq) and fe.dropped_frames() == []
        traj, want = fe.trajectory(), ref_fe.trajectory()
        assert sorted(traj) == sorted(want) and len(traj) == len(seq)
        assert max(np.abs(traj[i] - want[i]).max() for i in want) == 0.0
        assert fe.keyframe_frames() == ref_fe.keyframe_frames()
        assert up.new_keyframes == ref.update.new_keyframes
        assert np.array_equal(up.points, ref.update.points)
        assert fe.stats()["keyframes"] == len(ref_fe.keyframe_frames())
    finally:
        fe.close()


def test_a_checkpoint_mid_sequence_resumes_without_losing_or_repeating_updates(tmp_path):
    _, seq, factory = _setup(tmp_path)
    fe = ProcessSource(factory, seq)
    first = MapUpdate()
    try:
        while len(fe.keyframe_frames()) < 3 and not fe.exhausted():
            first = first.merge(fe.track(timeout=0.2))
        state = fe.state_dict()  # the child may have tracked more: those updates travel in the state
    finally:
        fe.close()
    assert not fe.exhausted() and not instances_in(state) and state["frontend"]["kind"] == "orb"
    resumed = ProcessSource(factory, seq)
    resumed.load_state_dict(state)
    try:
        second = _drain(resumed)
    finally:
        resumed.close()
    whole = first.merge(second)
    ref_fe = factory()
    ref = run_sequence(ref_fe, seq)
    assert whole.new_keyframes == ref.update.new_keyframes  # each once, none lost
    assert np.array_equal(whole.points, ref.update.points)
    traj, want = resumed.trajectory(), ref_fe.trajectory()
    assert sorted(traj) == sorted(want)
    assert max(np.abs(traj[i] - want[i]).max() for i in want) < 1e-9


def test_live_mode_drops_the_frames_it_is_too_slow_for(tmp_path):
    _, seq, factory = _setup(tmp_path)
    # 200x real time: the 16 frames (0.5 s at 30 Hz) arrive within a few milliseconds
    fe = LiveSource(factory, seq, rate=200.0)
    try:
        _drain(fe)
    finally:
        fe.close()
    dropped, tracked, lost = set(fe.dropped_frames()), set(fe.trajectory()), set(fe.lost_frames())
    assert dropped and not dropped & tracked and not dropped & lost
    assert len(dropped) + fe.frames_done == len(seq)
    assert fe.stats()["frames_dropped"] == len(dropped)


def test_prepared_frames_track_like_raw_ones_and_keep_their_feature_time(tmp_path):
    """OrbFrontend.prepare (features built ahead, as the frame source's thread does) changes
    nothing tracked, and "track" still counts the features' time."""
    _, seq, factory = _setup(tmp_path)
    raw, ahead = factory(), factory()
    for i in range(len(seq)):
        a, b = raw.process(seq[i]), ahead.process(ahead.prepare(seq[i]))
        assert a.kf_id == b.kf_id and (a.w2c is None) == (b.w2c is None)
        assert a.w2c is None or np.array_equal(a.w2c, b.w2c)
    assert raw.keyframe_frames() == ahead.keyframe_frames()
    feats, track = np.array(ahead.times["features"]), np.array(ahead.times["track"])
    assert (feats > 0).all() and (track >= feats).all()


@pytest.mark.parametrize("reader", ["thread", "process"])
def test_run_sequence_with_prefetch_gives_the_same_run(tmp_path, reader):
    _, seq, factory = _setup(tmp_path)
    plain_fe, ahead_fe = factory(), factory()
    plain = run_sequence(plain_fe, seq, frames=range(2, len(seq)))
    seen = []
    ahead = run_sequence(ahead_fe, seq, frames=range(2, len(seq)), prefetch=2, reader=reader,
                         on_frame=lambda frame, res: seen.append(frame.index))
    assert seen == list(range(2, len(seq)))
    assert [r.frame_index for r in ahead.results] == seen
    assert [r.kf_id for r in ahead.results] == [r.kf_id for r in plain.results]
    want = plain_fe.trajectory()
    assert max(np.abs(ahead_fe.trajectory()[i] - want[i]).max() for i in want) == 0.0
    assert np.array_equal(ahead.update.points, plain.update.points)
    # process_s still counts each frame's features (built in the reader thread)
    assert ahead.process_s >= sum(ahead_fe.times["features"])


class _FailsAt:
    """A sequence whose frame `bad` cannot be read (as a corrupt image file would)."""

    def __init__(self, seq, bad: int):
        self.seq, self.bad = seq, bad

    def __len__(self) -> int:
        return len(self.seq)

    def __getitem__(self, i: int):
        if i == self.bad:
            raise DataError(f"frame-{i:06d}.color.png: cannot decode")
        return self.seq[i]


def test_a_reader_process_error_reaches_the_caller_and_the_child_stops(tmp_path):
    import multiprocessing

    _, seq, factory = _setup(tmp_path)
    seen = []
    with pytest.raises(DataError, match="frame-000005.color.png"):
        run_sequence(factory(), _FailsAt(seq, 5), prefetch=2, reader="process",
                     on_frame=lambda frame, res: seen.append(frame.index))
    assert seen == [0, 1, 2, 3, 4]  # every frame before the bad one was tracked
    assert not [p for p in multiprocessing.active_children() if p.name == "segs-frames"]
    with pytest.raises(ConfigError, match="reader"):
        run_sequence(factory(), seq, prefetch=2, reader="fork")


def test_a_reader_process_from_a_script_without_a_main_guard_fails_at_once(tmp_path):
    """Python's spawn re-imports the main module: the child dies while starting; the call must
    raise, naming the guard, instead of hanging."""
    import subprocess
    import sys

    script = tmp_path / "unguarded.py"
    script.write_text(
        "from segs.config import compose, instantiate, make_sequence\n"
        "from segs.pipeline.sources import run_sequence\n"
        f"cfg = compose({BASE + ['data.n_frames=4']!r}, output_dir={str(tmp_path)!r})\n"
        "seq = make_sequence(cfg.data)\n"
        "run_sequence(instantiate(cfg.slam)(camera=seq.camera, sensor=seq.sensor), seq, prefetch=2, reader='process')\n")
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120)
    assert out.returncode != 0
    assert "__name__ == '__main__'" in out.stderr.splitlines()[-1]


def test_the_frame_source_prepares_frames_in_its_own_thread(tmp_path):
    import threading

    _, seq, _ = _setup(tmp_path)
    threads = []

    def prepare(frame):
        threads.append(threading.get_ident())
        return ("prepared", frame.index)

    got = [item for item, _, _ in CameraFrames(seq, 3, live=False, rate=1.0, prepare=prepare)]
    assert got == [("prepared", i) for i in range(3, len(seq))]
    assert len(threads) == len(seq) - 3 and threading.get_ident() not in threads


def test_live_pacing_waits_for_a_frame_and_skips_past_ones():
    ts = np.arange(10) / 30.0
    import time

    t0 = time.perf_counter()
    assert next_live(ts, 0, t0, 0.0, 1.0) == (0, [])
    assert next_live(ts, 1, t0 - 0.2, 0.0, 1.0) == (6, [1, 2, 3, 4, 5])  # 0.2 s late: frame 6 is due
    assert next_live(ts, 9, t0 - 5.0, 0.0, 1.0) == (9, [])  # never past the last frame
    t = time.perf_counter()
    assert next_live(ts, 3, t, 0.0, 1.0) == (3, [])  # early: waits about 0.1 s
    assert time.perf_counter() - t > 0.08


def test_a_failing_child_raises_in_the_parent(tmp_path):
    _, seq, _ = _setup(tmp_path)
    fe = ProcessSource(functools.partial(int, "not a frontend"), seq)
    try:
        with pytest.raises(RuntimeError, match="ValueError"):
            _drain(fe)
    finally:
        fe.close()


def test_bad_slam_mode_is_a_config_error(tmp_path):
    cfg, seq, _ = _setup(tmp_path, "slam_mode=threads")
    from segs.config import validate

    with pytest.raises(ConfigError, match="slam_mode"):
        validate(cfg)
    cfg, seq, _ = _setup(tmp_path, "slam_mode=live", "slam_rate=0")
    with pytest.raises(ConfigError, match="slam_rate"):
        validate(cfg)


@pytest.mark.slow
def test_track_and_train_run_with_the_frontend_in_a_process(tmp_path):
    from segs.track import run as track
    from segs.train import run as train

    cfg = compose(BASE + ["slam_mode=process"], output_dir=str(tmp_path / "track"))
    m = track(cfg, progress=False)
    assert m["slam_mode"] == "process" and m["frames_tracked"] == 16 and m["ate_rmse_m"] < 0.05
    cfg = compose(BASE + ["slam_mode=process", "trainer.max_steps=40", "callbacks.periodic_checkpoint.every_n_steps=0",
                          "callbacks.slam_bridge.min_initial_keyframes=2", "eval.save_renders=0", "eval.write_ply=false"],
                  output_dir=str(tmp_path / "train"))
    m = train(cfg)
    saved = json.loads((Path(cfg.paths.output_dir) / "metrics.json").read_text())
    assert saved["status"] == "finished" and saved["frames_tracked"] == 16
    assert saved["frames_dropped_live"] == 0 and np.isfinite(m["psnr"]) and m["ate_rmse_m"] < 0.05
    assert isinstance(make_source(cfg, make_sequence(cfg.data)), ProcessSource)
