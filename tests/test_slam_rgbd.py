"""ORB frontend on a synthetic RGB-D loop (exact depth and poses): accuracy and the MapUpdate contract."""
from __future__ import annotations

import numpy as np
import pytest

from segs.config import slam_frontend
from segs.data.synthetic import SyntheticSequence
from segs.pipeline.sources import run_sequence
from segs.trajectory import ate


@pytest.fixture(scope="module")
def rgbd_loop():
    # 1.2 laps (the 60-frame lap's step): the start is seen again by enough keyframes for three
    # consistent loop detections; a single lap closes on its last two keyframes only
    seq = SyntheticSequence(sensor="rgbd", n_frames=72, width=320, height=240, trajectory="loop", speed=71 / 59,
                            seed=0)
    fe = slam_frontend(seq.camera, "rgbd")
    return seq, fe, run_sequence(fe, seq)


def test_rgbd_tracks_every_frame_with_mm_ate(rgbd_loop):
    seq, fe, run = rgbd_loop
    traj = fe.trajectory()
    assert fe.lost_frames() == []
    assert sorted(traj) == list(range(len(seq)))
    assert all(r.tracked for r in run.results)
    assert ate(seq.timestamps, traj, seq.gt_poses, "se3")["rmse"] < 0.006


def test_rgbd_poses_are_rigid_w2c(rgbd_loop):
    _, fe, _ = rgbd_loop
    for w2c in fe.trajectory().values():
        R = w2c[:3, :3]
        assert w2c.shape == (4, 4) and np.allclose(w2c[3], [0, 0, 0, 1])
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-9) and np.linalg.det(R) > 0


def test_map_update_contract(rgbd_loop):
    seq, fe, run = rgbd_loop
    up = run.update
    kf_frames = fe.keyframe_frames()
    assert kf_frames, "no keyframes"
    # every keyframe still in the map was announced once, with a pose; ids are never reused
    assert len(up.new_keyframes) == len(set(up.new_keyframes))
    assert set(kf_frames) <= set(up.new_keyframes)
    assert set(up.new_keyframes) <= set(up.poses)  # culled keyframes too (recomposed from the parent)
    for k, idx in kf_frames.items():
        assert 0 <= idx < len(seq)
        assert np.allclose(up.poses[k], fe.trajectory()[idx], atol=1e-9)
    # points: finite, coloured in [0,1], tagged with a keyframe that was announced
    m = len(up.points)
    assert m > 1000
    assert up.points.shape == (m, 3) and up.colors.shape == (m, 3) and up.point_kf.shape == (m,)
    assert np.isfinite(up.points).all()
    assert up.colors.dtype == np.float32 and up.colors.min() >= 0 and up.colors.max() <= 1
    assert set(np.unique(up.point_kf).tolist()) <= set(up.new_keyframes)
    # points lie on the room's surfaces: depth-consistent in the keyframe that created them
    some = np.flatnonzero(up.point_kf == up.new_keyframes[0])[:200]
    kf0 = fe.map.culled.get(up.new_keyframes[0]) or fe.map.kfs[up.new_keyframes[0]]
    frame = seq[kf0.frame_index]
    pc = up.points[some] @ up.poses[up.new_keyframes[0]][:3, :3].T + up.poses[up.new_keyframes[0]][:3, 3]
    K = seq.camera.K
    u = np.clip(np.rint(K[0, 0] * pc[:, 0] / pc[:, 2] + K[0, 2]).astype(int), 0, seq.camera.width - 1)
    v = np.clip(np.rint(K[1, 1] * pc[:, 1] / pc[:, 2] + K[1, 2]).astype(int), 0, seq.camera.height - 1)
    assert np.median(np.abs(frame.depth[v, u] - pc[:, 2])) < 0.02


def test_loop_detected_and_corrections_reported(rgbd_loop):
    _, fe, run = rgbd_loop
    assert fe.loop.loops, "the loop back to the start was not detected"
    corr = run.update.corrections
    assert corr
    for T in corr.values():
        R = T[:3, :3]
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-6)  # RGB-D: rigid (scale 1)
        assert np.allclose(T[3], [0, 0, 0, 1])


def test_single_thread_mode_is_deterministic():
    seq = SyntheticSequence(sensor="rgbd", n_frames=16, width=320, height=240, trajectory="loop", seed=1)
    trajs = []
    for _ in range(2):
        fe = slam_frontend(seq.camera, "rgbd")
        run_sequence(fe, seq)
        trajs.append(fe.trajectory())
    assert trajs[0].keys() == trajs[1].keys()
    for k in trajs[0]:
        assert np.array_equal(trajs[0][k], trajs[1][k])
