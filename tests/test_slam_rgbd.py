"""ORB frontend on synthetic RGB-D sequences (exact depth and poses)."""
from __future__ import annotations

import pytest

from segs.data.synthetic import SyntheticSequence
from segs.slam.orb import OrbFrontend
from segs.slam.runner import run_sequence
from segs.trajectory import ate


@pytest.fixture(scope="module")
def rgbd_loop():
    seq = SyntheticSequence(sensor="rgbd", n_frames=60, width=320, height=240, trajectory="loop", seed=0)
    fe = OrbFrontend(seq.camera, "rgbd")
    return seq, fe, run_sequence(fe, seq)


def test_rgbd_tracks_every_frame_with_mm_ate(rgbd_loop):
    seq, fe, run = rgbd_loop
    traj = fe.trajectory()
    assert fe.lost_frames() == []
    assert sorted(traj) == list(range(len(seq)))
    assert ate(seq.timestamps, traj, seq.gt_poses, "se3")["rmse"] < 0.006
