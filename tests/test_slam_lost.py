"""Lost tracking: blank frames are reported lost; tracking restarts or relocalizes cleanly."""
from __future__ import annotations

from segs.config import slam_frontend
from segs.data.synthetic import SyntheticSequence
from segs.pipeline.sources import run_sequence
from segs.trajectory import ate


def test_blank_stretch_is_reported_and_recovered():
    # 1.2 laps, as tests/test_slam_rgbd.py: enough keyframes revisit the start for a detection
    seq = SyntheticSequence(sensor="rgbd", n_frames=72, width=320, height=240, trajectory="loop", speed=71 / 59,
                            blank_frames=[(20, 26)], seed=0)
    fe = slam_frontend(seq.camera, "rgbd")
    run = run_sequence(fe, seq)
    lost = fe.lost_frames()
    assert set(range(20, 26)) <= set(lost)
    assert all(not r.tracked for r in run.results if r.frame_index in lost)
    traj = fe.trajectory()
    assert set(traj).isdisjoint(lost)
    # relocalization, or a new map segment after restart_after_lost frames without it
    assert max(lost) <= 26 + 2 * fe.cfg.tracking.restart_after_lost, "tracking did not resume after the blank"
    assert set(range(max(lost) + 1, len(seq))) <= set(traj)
    assert len(traj) + len(lost) == len(seq)
    # the segment after the restart is re-attached by the loop closure
    assert ate(seq.timestamps, traj, seq.gt_poses, "se3")["rmse"] < 0.02


def test_blank_start_and_relocalization_without_restart():
    seq = SyntheticSequence(sensor="rgbd", n_frames=30, width=320, height=240, trajectory="orbit", speed=0.3,
                            blank_frames=[(0, 3), (12, 15)], seed=0)
    fe = slam_frontend(seq.camera, "rgbd", tracking={"restart_after_lost": 0})
    run_sequence(fe, seq)
    lost = fe.lost_frames()
    assert {0, 1, 2, 12, 13, 14} <= set(lost)
    traj = fe.trajectory()
    assert 15 in traj or 16 in traj, "no relocalization after the blank frames"
    assert ate(seq.timestamps, traj, seq.gt_poses, "se3")["rmse"] < 0.02


def test_depth_poor_start_waits_init_wait_frames_then_starts_with_fewer_points():
    """Depth only in the left 30 % of every image (about 360-470 keypoints with depth, under
    min_init_points = 500): the map starts after init_wait frames with min_init_points_late
    and the frames after it are tracked; with the late minimum at 500 (and no two-view start)
    nothing ever starts."""
    from dataclasses import replace

    seq = SyntheticSequence(sensor="rgbd", n_frames=24, width=320, height=240, trajectory="orbit", speed=0.3, seed=0)

    def depth_poor(i):
        f = seq[i]
        d = f.depth.copy()
        d[:, int(0.3 * d.shape[1]):] = 0
        return replace(f, depth=d)

    frames = [depth_poor(i) for i in range(len(seq))]
    for late, first in ((150, 10), (500, None)):
        fe = slam_frontend(seq.camera, "rgbd", tracking={"init_wait": 10, "min_init_points_late": late},
                         init={"depth_scale_points": 0})
        for f in frames if first else frames[:14]:  # 500: past init_wait is enough to show it
            fe.process(f)
        traj = fe.trajectory()
        if first is None:
            assert not traj
            continue
        assert min(traj) == first and set(range(first)) <= set(fe.lost_frames())
        assert len(traj) >= len(seq) - first - 2
        assert ate(seq.timestamps, traj, seq.gt_poses, "se3")["rmse"] < 0.02


def test_depth_poor_start_from_two_views_is_metric():
    """90 % of every depth map in holes (about 20-110 keypoints with depth, never the 150 of
    min_init_points_late): the map starts from two views scaled by the depth its points have,
    the frames after it are tracked at the true scale (SE(3) ATE, Sim(3) scale near 1); with the
    fallback off (init.depth_scale_points 0) no map starts."""
    from segs.data.stress import apply_stress

    base = SyntheticSequence(sensor="rgbd", n_frames=60, width=320, height=240, trajectory="orbit", speed=0.5, seed=0)
    seq = apply_stress(base, "depth_holes", 0.9)
    frames = [seq[i] for i in range(len(seq))]
    assert max(int((f.depth > 0).mean() * 1000) for f in frames) < 150  # under 15 % of the pixels
    off = slam_frontend(seq.camera, "rgbd", init={"depth_scale_points": 0})
    for f in frames[:30]:
        off.process(f)
    assert not off.trajectory()
    fe = slam_frontend(seq.camera, "rgbd")
    for f in frames:
        fe.process(f)
    traj = fe.trajectory()
    assert min(traj) > fe.cfg.tracking.init_wait  # not a depth start at frame 0
    assert set(range(min(traj), len(seq))) <= set(traj), "frames lost after the two-view start"
    assert len(traj) >= 40
    assert ate(seq.timestamps, traj, seq.gt_poses, "se3")["rmse"] < 0.03
    assert abs(ate(seq.timestamps, traj, seq.gt_poses, "sim3")["scale"] - 1.0) < 0.05
