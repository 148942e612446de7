"""Synthetic room generator: geometry, stereo, exposure, blank frames, loop closure, speed."""
import time

import cv2
import numpy as np
import pytest

from segs.data.synthetic import SyntheticSequence, exposure, trajectory_poses
from segs.errors import ConfigError


def _bilinear(img, u, v):
    return cv2.remap(img, u.astype(np.float32), v.astype(np.float32), cv2.INTER_LINEAR)


def _reproject(frame_i, frame_j):
    """Pixels of i (depth, pose) projected into j: (u_j, v_j, z_j, mask)."""
    cam = frame_i.camera
    v, u = np.mgrid[0 : cam.height, 0 : cam.width].astype(np.float64)
    z = frame_i.depth.astype(np.float64)
    pc = np.stack([(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z, np.ones_like(z)], -1)
    rel = np.linalg.inv(frame_j.pose_c2w) @ frame_i.pose_c2w
    q = pc @ rel.T
    zj = q[..., 2]
    uj = cam.fx * q[..., 0] / zj + cam.cx
    vj = cam.fy * q[..., 1] / zj + cam.cy
    inside = (zj > 0.1) & (uj > 1) & (vj > 1) & (uj < cam.width - 2) & (vj < cam.height - 2)
    return uj, vj, zj, inside


def test_shapes_and_sensors():
    for sensor in ("mono", "stereo", "rgbd"):
        seq = SyntheticSequence(sensor=sensor, n_frames=5, width=64, height=48)
        f = seq[2]
        assert len(seq) == 5 and seq.sensor == sensor
        assert f.rgb.shape == (48, 64, 3) and f.rgb.dtype == np.float32
        assert 0.0 <= f.rgb.min() and f.rgb.max() <= 1.0
        assert (f.depth is not None) == (sensor == "rgbd")
        assert (f.right is not None) == (sensor == "stereo")
        assert (seq.camera.baseline is not None) == (sensor == "stereo")
        assert f.timestamp == pytest.approx(2 / 30) and f.pose_c2w.shape == (4, 4)
        np.testing.assert_allclose(seq.timestamps, np.arange(5) / 30)
        assert seq.gt_poses.shape == (5, 4, 4)


def test_camera_intrinsics_follow_fov():
    seq = SyntheticSequence(n_frames=2, width=320, height=240, fov_deg=90.0)
    assert seq.camera.fx == pytest.approx(160.0) and seq.camera.fy == pytest.approx(160.0)
    assert (seq.camera.cx, seq.camera.cy) == (159.5, 119.5)


@pytest.mark.parametrize("trajectory", ["loop", "line", "orbit", "pan", "forward"])
def test_poses_are_rigid_and_inside_free_space(trajectory):
    seq = SyntheticSequence(sensor="rgbd", n_frames=40, width=40, height=30, trajectory=trajectory)
    rot = seq.gt_poses[:, :3, :3]
    np.testing.assert_allclose(rot @ rot.transpose(0, 2, 1), np.broadcast_to(np.eye(3), rot.shape), atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-9)
    assert min(f.depth.min() for f in seq) > 0.3  # never inside or touching furniture


def test_depth_reprojects_with_same_colour():
    seq = SyntheticSequence(sensor="rgbd", n_frames=60)
    fi, fj = seq[10], seq[11]
    uj, vj, zj, inside = _reproject(fi, fj)
    depth_j = _bilinear(fj.depth, uj, vj)
    visible = inside & (np.abs(depth_j - zj) < 0.01 * zj)
    assert visible.mean() > 0.5
    colour_j = _bilinear(fj.rgb, uj, vj)
    err = np.abs(colour_j - fi.rgb).mean(-1)[visible]
    assert np.median(err) < 0.02 and np.mean(err) < 0.05


def test_depth_is_z_depth_not_ray_length():
    seq = SyntheticSequence(sensor="rgbd", n_frames=3, trajectory="line")
    f = seq[0]
    # A ray through a corner pixel is longer than its z-depth; the points must lie on the
    # room or furniture surfaces, so the 3D points of neighbouring pixels on a wall are planar.
    cam = f.camera
    v, u = np.mgrid[0:cam.height, 0:cam.width]
    x = (u - cam.cx) / cam.fx * f.depth
    y = (v - cam.cy) / cam.fy * f.depth
    pw = np.stack([x, y, f.depth], -1) @ f.pose_c2w[:3, :3].T + f.pose_c2w[:3, 3]
    on_plane = np.zeros(pw.shape[:2], bool)
    for axis, levels in ((0, (-3.0, 3.0)), (1, (-2.5, 2.5)), (2, (0.0, 3.0))):
        for level in levels:
            on_plane |= np.abs(pw[..., axis] - level) < 1e-3
    from segs.data.synthetic_scene import OBSTACLES
    for lo, hi in OBSTACLES:
        for axis in range(3):
            for level in (lo[axis], hi[axis]):
                on_plane |= np.abs(pw[..., axis] - level) < 1e-3
    assert on_plane.mean() > 0.999


def test_stereo_disparity_matches_depth():
    kw = dict(n_frames=20, trajectory="loop", baseline=0.1)
    stereo, rgbd = SyntheticSequence(sensor="stereo", **kw), SyntheticSequence(sensor="rgbd", **kw)
    fs, fd = stereo[5], rgbd[5]
    np.testing.assert_array_equal(fs.rgb, fd.rgb)
    cam = stereo.camera
    assert cam.baseline == 0.1
    v, u = np.mgrid[0 : cam.height, 0 : cam.width].astype(np.float32)
    disparity = cam.fx * cam.baseline / fd.depth
    ur = u - disparity
    warped = _bilinear(fs.right, ur, v)
    ok = ur > 2
    err = np.abs(warped - fs.rgb).mean(-1)[ok]
    assert np.median(err) < 0.02
    wrong = np.abs(_bilinear(fs.right, u - 0.7 * disparity, v) - fs.rgb).mean(-1)[ok]
    assert np.median(wrong) > 2 * np.median(err)


def test_exposure_changes_brightness_not_geometry():
    plain = SyntheticSequence(sensor="rgbd", n_frames=30)
    bright = SyntheticSequence(sensor="rgbd", n_frames=30, exposure_change=0.8)
    means = [bright[i].rgb.mean() / plain[i].rgb.mean() for i in range(0, 30, 3)]
    assert max(means) > 1.2 and min(means) < 0.8
    np.testing.assert_array_equal(bright[4].depth, plain[4].depth)
    gains = np.array([exposure(i, 0.8) for i in range(30)])
    assert np.all(np.abs(np.diff(np.log2(gains), axis=0)) < 0.35)  # smooth in the index
    np.testing.assert_array_equal(exposure(7, 0.0), np.ones(3, np.float32))


def test_blank_frames_are_uniform_with_exact_depth():
    seq = SyntheticSequence(sensor="rgbd", n_frames=20, blank_frames=[3, (10, 12)])
    assert seq.blank == {3, 10, 11}
    for i in (3, 10, 11):
        assert np.ptp(seq[i].rgb) == 0.0 and seq[i].depth.min() > 0
    assert np.ptp(seq[12].rgb) > 0.5
    stereo = SyntheticSequence(sensor="stereo", n_frames=20, blank_frames=range(2, 4))
    assert np.ptp(stereo[2].right) == 0.0 and np.ptp(stereo[4].right) > 0.5


def test_loop_closes_and_speed_scales_motion():
    for speed in (1.0, 2.0):
        poses = trajectory_poses("loop", 60, speed)
        np.testing.assert_allclose(poses[0], poses[-1], atol=1e-9)
        assert np.linalg.norm(poses[:, :3, 3] - poses[0, :3, 3], axis=1).max() > 2.0
    step = lambda p: np.linalg.norm(np.diff(p[:, :3, 3], axis=0), axis=1).mean()  # noqa: E731
    for kind in ("loop", "line", "orbit"):
        slow, fast = trajectory_poses(kind, 61, 1.0), trajectory_poses(kind, 61, 2.0)
        assert step(fast) == pytest.approx(2 * step(slow), rel=0.05)
    pan = trajectory_poses("pan", 61, 1.0)  # rotation in place, once around
    np.testing.assert_allclose(pan[:, :3, 3], np.broadcast_to(pan[0, :3, 3], (61, 3)), atol=1e-12)
    np.testing.assert_allclose(pan[0], pan[-1], atol=1e-9)
    line = trajectory_poses("line", 61, 2.0)
    np.testing.assert_allclose(line[0], line[-1], atol=1e-9)


def test_forward_drives_down_the_corridor():
    seq = SyntheticSequence(sensor="rgbd", n_frames=21, width=64, height=48, trajectory="forward", speed=1.0)
    pos = seq.gt_poses[:, :3, 3]
    steps = np.diff(pos, axis=0)
    assert np.all(steps[:, 1] > 0)  # always forward (+y), weaving sideways
    assert np.linalg.norm(steps, axis=1).sum() == pytest.approx(24.0, rel=0.02)  # 24 m per unit speed
    assert np.all(seq.gt_poses[:, 1, 2] > 0.95)  # the optical axis looks down the corridor
    assert np.ptp(pos[:, 0]) > 0.5
    depths = np.concatenate([seq[i].depth.ravel() for i in (0, 10, 20)])
    assert depths.min() < 3.0 and depths.max() > 30.0  # a street-like depth range
    assert seq.name == "synthetic_forward_rich"
    fast = trajectory_poses("forward", 21, 2.0)
    np.testing.assert_allclose(np.diff(fast[:, :3, 3], axis=0)[:, 1], 2 * steps[:, 1], rtol=1e-9)
    with pytest.raises(ConfigError, match="corridor ends"):
        SyntheticSequence(trajectory="forward", speed=3.5)


def test_corridor_reprojects_with_same_colour():
    """Consecutive forward frames 0.4 m apart agree in colour (mip-mapped texture, exact depth)."""
    seq = SyntheticSequence(sensor="rgbd", n_frames=61, trajectory="forward", speed=1.0)
    fi, fj = seq[10], seq[11]
    uj, vj, zj, inside = _reproject(fi, fj)
    depth_j = _bilinear(fj.depth, uj, vj)
    visible = inside & (np.abs(depth_j - zj) < 0.01 * zj)
    assert visible.mean() > 0.5
    err = np.abs(_bilinear(fj.rgb, uj, vj) - fi.rgb).mean(-1)[visible]
    assert np.median(err) < 0.03


def test_room_layout_is_unchanged_by_the_corridor():
    from segs.data.synthetic_scene import get_scene
    room = get_scene("rich", 0)
    assert room.mip_levels == 1 and room.atlas.shape[1] == 4096 and not room._transposed.any()
    corridor = get_scene("rich", 0, "corridor")
    assert corridor.mip_levels > 1 and corridor._transposed.any()  # floor and ceiling lie down
    assert corridor.atlas.nbytes < 30e6


def test_texture_knob_controls_orb_features():
    orb = cv2.ORB_create(nfeatures=3000)

    def count(seq):
        return np.median([len(orb.detect((seq[i].rgb * 255).astype(np.uint8), None))
                          for i in range(0, 60, 10)])

    assert count(SyntheticSequence(sensor="mono", texture="rich")) > 500
    assert count(SyntheticSequence(sensor="mono", texture="poor")) < 50
    mixed = count(SyntheticSequence(sensor="mono", texture="mixed"))
    assert 0 < mixed


def test_seed_changes_textures_not_poses():
    a, b = SyntheticSequence(n_frames=5, seed=0), SyntheticSequence(n_frames=5, seed=1)
    np.testing.assert_array_equal(a.gt_poses, b.gt_poses)
    np.testing.assert_array_equal(a[1].depth, b[1].depth)
    assert np.abs(a[1].rgb - b[1].rgb).mean() > 0.05


def test_cache_returns_independent_copies():
    seq = SyntheticSequence(n_frames=5)
    f = seq[1]
    f.rgb[:] = 0
    f.pose_c2w[:] = 0
    assert seq[1].rgb.max() > 0 and seq[1].pose_c2w[3, 3] == 1
    assert seq[-1].index == 4
    with pytest.raises(IndexError):
        seq[5]


def test_pickles_without_the_scene():
    import pickle
    seq = SyntheticSequence(n_frames=4, texture="mixed")
    seq[0]
    blob = pickle.dumps(seq)
    assert len(blob) < 4_000_000
    np.testing.assert_array_equal(pickle.loads(blob)[2].rgb, seq[2].rgb)


def test_render_speed():
    seq = SyntheticSequence(sensor="rgbd", n_frames=100)
    seq[0]
    start = time.perf_counter()
    for i in range(1, 21):
        seq[i]
    per_frame = (time.perf_counter() - start) / 20
    assert per_frame < 0.03, f"{per_frame * 1000:.1f} ms per 320x240 frame"


@pytest.mark.parametrize("kwargs", [dict(sensor="depth"), dict(trajectory="spiral"),
                                    dict(texture="wood"), dict(n_frames=0), dict(fov_deg=180),
                                    dict(trajectory="forward", speed=-1.0),
                                    dict(sensor="stereo", baseline=0.0), dict(blank_frames=["x"]),
                                    dict(blank_frames=[(1, 2, 3)])])
def test_bad_configuration(kwargs):
    with pytest.raises(ConfigError):
        SyntheticSequence(**kwargs)
