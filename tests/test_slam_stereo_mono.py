"""ORB frontend on synthetic stereo and monocular sequences: loop closing and scale-aligned ATE."""
from __future__ import annotations

import pytest

from segs.config import slam_frontend
from segs.data.synthetic import SyntheticSequence
from segs.pipeline.sources import run_sequence
from segs.trajectory import ate


@pytest.fixture(scope="module")
def stereo_loop():
    # 1.2 laps, as tests/test_slam_rgbd.py: enough keyframes revisit the start for a detection
    return SyntheticSequence(sensor="stereo", n_frames=72, width=320, height=240, trajectory="loop",
                             speed=71 / 59, seed=0)


@pytest.mark.slow
def test_stereo_loop_closing_reduces_drift(stereo_loop):
    seq = stereo_loop
    fe = slam_frontend(seq.camera, "stereo")
    snap: dict = {}

    def on_frame(frame, res):  # the trajectory just before and just after the loop correction
        if fe.loop.loops and "after" not in snap:
            snap["after"] = fe.trajectory()
        elif not fe.loop.loops:
            snap["before"] = fe.trajectory()

    run = run_sequence(fe, seq, on_frame=on_frame)
    assert fe.lost_frames() == []
    assert fe.loop.loops, "loop not detected"
    assert run.update.corrections
    frames = sorted(snap["before"])
    before = ate(seq.timestamps, snap["before"], seq.gt_poses, "se3")["rmse"]
    after = ate(seq.timestamps, {i: snap["after"][i] for i in frames}, seq.gt_poses, "se3")["rmse"]
    assert after < 0.7 * before
    assert ate(seq.timestamps, fe.trajectory(), seq.gt_poses, "se3")["rmse"] < 0.03


def test_mono_scale_aligned_ate():
    seq = SyntheticSequence(sensor="mono", n_frames=60, width=320, height=240, trajectory="orbit", speed=0.5, seed=0)
    fe = slam_frontend(seq.camera, "mono")
    run = run_sequence(fe, seq)
    traj = fe.trajectory()
    # two-view initialization: the frames before it are reported lost, never invented
    assert len(traj) >= len(seq) - 5
    assert set(traj).isdisjoint(fe.lost_frames())
    assert set(traj) | set(fe.lost_frames()) == set(range(len(seq)))
    res = ate(seq.timestamps, traj, seq.gt_poses, "sim3")
    assert res["rmse"] < 0.02
    assert len(run.update.points) > 500 and len(fe.keyframe_frames()) >= 3
