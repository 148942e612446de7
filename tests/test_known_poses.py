"""The known-poses frontend on synthetic sequences with exact depth and poses."""
from __future__ import annotations

import numpy as np
import pytest

from segs.config import slam_frontend
from segs.data.synthetic import SyntheticSequence
from segs.errors import ConfigError


def _run(sensor: str, frames: int = 24, **kw):
    seq = SyntheticSequence(sensor=sensor, n_frames=60, width=160, height=120, trajectory="loop", seed=1)
    fe = slam_frontend(seq.camera, sensor, "known_poses", keyframe_every=2, kf_translation=10.0, kf_rotation_deg=90, n_features=400, **kw)
    for i in range(frames):
        fe.process(seq[i])
    return seq, fe, fe.poll()


def _depth_error(seq, fe, update) -> np.ndarray:
    """|z of each new point - depth map| / depth in the keyframe that created it."""
    depth_seq = SyntheticSequence(sensor="rgbd", n_frames=60, width=160, height=120, trajectory="loop", seed=1)
    errs = []
    c = seq.camera
    for kf_id, frame_index in fe.keyframe_frames().items():
        pts = update.points[update.point_kf == kf_id]
        w2c = update.poses[kf_id]
        cam = pts @ w2c[:3, :3].T + w2c[:3, 3]
        u = np.round(c.fx * cam[:, 0] / cam[:, 2] + c.cx).astype(int)
        v = np.round(c.fy * cam[:, 1] / cam[:, 2] + c.cy).astype(int)
        inside = (u >= 0) & (u < c.width) & (v >= 0) & (v < c.height)
        depth = depth_seq[frame_index].depth
        errs.append(np.abs(cam[inside, 2] - depth[v[inside], u[inside]]) / depth[v[inside], u[inside]])
    return np.concatenate(errs)


def test_rgbd_points_lie_on_the_surfaces():
    seq, fe, update = _run("rgbd")
    assert len(update.new_keyframes) == 12 and len(update.points) > 300
    assert fe.lost_frames() == [] and len(fe.trajectory()) == 24
    err = _depth_error(seq, fe, update)
    assert np.median(err) < 0.01


def test_mono_triangulated_points_lie_on_the_surfaces():
    seq, fe, update = _run("mono")
    assert len(update.points) > 100
    err = _depth_error(seq, fe, update)
    assert np.median(err) < 0.05  # triangulation at 160x120: ~0.3 px noise


def test_stereo_points_lie_on_the_surfaces():
    seq, fe, update = _run("stereo")
    assert len(update.points) > 100
    assert np.median(_depth_error(seq, fe, update)) < 0.05


def test_points_are_not_lifted_twice():
    seq, fe, update = _run("rgbd")
    per_kf = np.bincount(update.point_kf)
    assert per_kf[0] > per_kf[1:].mean()  # later keyframes reuse what the previous one lifted


def test_frames_without_ground_truth_are_reported_lost():
    seq = SyntheticSequence(sensor="rgbd", n_frames=4, width=64, height=48)
    fe = slam_frontend(seq.camera, "rgbd", "known_poses")
    frames = list(seq)
    frames[2].pose_c2w = None
    results = [fe.process(f) for f in frames]
    assert not results[2].tracked and fe.lost_frames() == [2] and 2 not in fe.trajectory()


def test_bad_parameters_raise_config_errors():
    cam = SyntheticSequence(sensor="rgbd", n_frames=2, width=64, height=48).camera
    with pytest.raises(ConfigError, match="keyframe_every"):
        slam_frontend(cam, "rgbd", "known_poses", keyframe_every=0)
