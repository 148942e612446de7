"""Stress generators (segs.data.stress): level 0 is the identity, higher levels do what they say."""
from __future__ import annotations

import numpy as np
import pytest

from segs.config import compose, make_sequence
from segs.data.frame import Camera, Frame, Sequence
from segs.data.stress import KINDS, StressedSequence, apply_stress, hole_mask, line_kernel
from segs.data.synthetic import SyntheticSequence
from segs.errors import ConfigError

LEVELS = {"exposure": 2, "motion_blur": 8, "fast_motion": 2, "dropped_frames": 0.4, "noise": 16,
          "depth_holes": 0.5, "low_texture": 0.8}  # fmt: skip


class Frames(Sequence):
    """A sequence of given images (constant depth 2 m, identity-ish poses)."""

    def __init__(self, images: list[np.ndarray], sensor: str = "rgbd"):
        h, w = images[0].shape[:2]
        self.images, self.sensor, self.name = images, sensor, "frames"
        self.camera = Camera(50.0, 50.0, (w - 1) / 2, (h - 1) / 2, w, h, 0.1 if sensor == "stereo" else None)
        self.timestamps = np.arange(len(images)) / 30.0
        self.gt_poses = np.stack([np.eye(4) for _ in images])
        self.gt_poses[:, 0, 3] = np.arange(len(images))

    def __len__(self):
        return len(self.images)

    def __getitem__(self, i):
        rgb = self.images[i].copy()
        depth = np.full(rgb.shape[:2], 2.0, np.float32) if self.sensor == "rgbd" else None
        right = rgb.copy() if self.sensor == "stereo" else None
        return Frame(i, float(self.timestamps[i]), rgb, self.camera, depth, right, self.gt_poses[i].copy(), f"{i:06d}")


@pytest.fixture(scope="module")
def room():
    return SyntheticSequence(sensor="rgbd", n_frames=20, width=64, height=48)


def _same(a: Frame, b: Frame) -> bool:
    arrays = [(a.rgb, b.rgb), (a.depth, b.depth), (a.right, b.right), (a.pose_c2w, b.pose_c2w)]
    return a.index == b.index and a.timestamp == b.timestamp and all(
        (x is None and y is None) or (x.dtype == y.dtype and np.array_equal(x, y)) for x, y in arrays)  # fmt: skip


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_level_zero_is_the_identity_bit_for_bit(kind, room):
    seq = apply_stress(room, kind, 0)
    assert len(seq) == len(room) and seq.name == room.name and seq.sensor == room.sensor and seq.camera == room.camera
    np.testing.assert_array_equal(seq.timestamps, room.timestamps)
    np.testing.assert_array_equal(seq.gt_poses, room.gt_poses)
    assert all(_same(seq[i], room[i]) for i in range(len(room)))


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_higher_levels_change_frames_deterministically(kind, room):
    a, b = apply_stress(room, kind, LEVELS[kind], seed=3), apply_stress(room, kind, LEVELS[kind], seed=3)
    assert all(_same(a[i], b[i]) for i in reversed(range(len(a))))  # read order does not matter
    changed = [not _same(a[i], room[int(a.base_indices[i])]) for i in range(len(a))] if len(a) == len(room) else [True]
    assert any(changed)
    for i in range(len(a)):
        f = a[i]
        assert f.index == i and f.rgb.dtype == np.float32 and 0 <= f.rgb.min() and f.rgb.max() <= 1
        np.testing.assert_array_equal(f.pose_c2w, a.gt_poses[i])
        assert f.timestamp == a.timestamps[i]


def test_exposure_is_a_gain_and_white_balance_step():
    img = np.full((8, 8, 3), 0.4, np.float32)
    seq = apply_stress(Frames([img] * 10), "exposure", 1.0, at=0.5)
    assert all(np.array_equal(seq[i].rgb, img) for i in range(5))
    after = seq[7].rgb[0, 0]
    np.testing.assert_allclose(after, 0.4 * 2.0 ** (-1.0 + 0.25 * np.array([1, 0, -1])), rtol=1e-6)
    up = apply_stress(Frames([img] * 10), "exposure", 2.0, direction="up")[9].rgb
    assert up.max() == 1.0  # brighter and clipped


def test_motion_blur_spreads_a_point_along_a_line_of_the_level_length():
    img = np.zeros((21, 100, 3), np.float32)
    img[10, 50] = 1.0
    out = apply_stress(Frames([img]), "motion_blur", 10.0)[0].rgb[..., 0]  # 10 % of 100 px
    assert out.sum() == pytest.approx(1.0, rel=1e-4)
    rows, cols = np.nonzero(out > 1e-4)
    assert set(rows) == {10} and 9 <= cols.max() - cols.min() + 1 <= 11
    vertical = apply_stress(Frames([img]), "motion_blur", 10.0, angle_deg=90)[0].rgb[..., 0]
    assert set(np.nonzero(vertical > 1e-4)[1]) == {50}
    k = line_kernel(5.0, 30.0)
    assert k.sum() == pytest.approx(1.0) and k.shape[0] % 2 == 1


def test_motion_blur_fraction_blurs_only_some_frames(room):
    seq = apply_stress(room, "motion_blur", 8, fraction=0.5, seed=1)
    blurred = [not np.array_equal(seq[i].rgb, room[i].rgb) for i in range(len(room))]
    assert 0 < sum(blurred) < len(room)


def test_fast_motion_keeps_every_k_th_frame(room):
    seq = apply_stress(room, "fast_motion", 2)
    np.testing.assert_array_equal(seq.base_indices, np.arange(0, 20, 3))
    np.testing.assert_array_equal(seq.timestamps, room.timestamps[::3])
    np.testing.assert_array_equal(seq.gt_poses, room.gt_poses[::3])
    np.testing.assert_array_equal(seq[2].rgb, room[6].rgb)
    assert seq[2].index == 2


def test_dropped_frames_removes_bursts_of_the_given_fraction(room):
    seq = apply_stress(room, "dropped_frames", 0.4, burst=3, seed=5)
    kept = seq.base_indices
    assert len(seq) == 12 and kept[0] == 0 and np.all(np.diff(kept) > 0)
    assert np.diff(kept).max() >= 2  # a gap
    np.testing.assert_array_equal(seq.timestamps, room.timestamps[kept])
    np.testing.assert_array_equal(seq[5].rgb, room[int(kept[5])].rgb)
    assert not np.array_equal(apply_stress(room, "dropped_frames", 0.4, seed=6).base_indices, kept)


def test_noise_has_the_level_sigma_and_leaves_depth():
    img = np.full((64, 64, 3), 0.5, np.float32)
    f = apply_stress(Frames([img]), "noise", 10.0)[0]
    assert np.std(f.rgb - img) == pytest.approx(10 / 255, rel=0.05)
    assert np.all(f.depth == 2.0)
    stereo = apply_stress(Frames([img], sensor="stereo"), "noise", 10.0)[0]
    assert not np.array_equal(stereo.rgb, stereo.right)  # independent noise in both images


def test_depth_holes_cover_the_fraction_and_only_rgbd():
    f = apply_stress(Frames([np.zeros((60, 80, 3), np.float32)]), "depth_holes", 0.3)[0]
    holes = (f.depth == 0).mean()
    assert 0.3 <= holes < 0.45 and np.all(f.rgb == 0)
    assert hole_mask((10, 10), 1.0, 0.1, np.random.default_rng(0)).all()
    with pytest.raises(ConfigError, match="data.stress"):
        apply_stress(Frames([np.zeros((8, 8, 3), np.float32)], sensor="mono"), "depth_holes", 0.3)


def test_low_texture_scales_contrast_around_the_mean():
    rng = np.random.default_rng(0)
    img = rng.uniform(0.2, 0.8, (32, 32, 3)).astype(np.float32)
    out = apply_stress(Frames([img]), "low_texture", 0.75)[0].rgb
    np.testing.assert_allclose(out.mean((0, 1)), img.mean((0, 1)), atol=1e-5)
    np.testing.assert_allclose(out.std((0, 1)), 0.25 * img.std((0, 1)), rtol=1e-4)
    assert np.ptp(apply_stress(Frames([img]), "low_texture", 1.0)[0].rgb[..., 0]) < 1e-6


@pytest.mark.parametrize("kind,level,options,needle", [
    ("blur", 1, {}, "data.stress.kind"), ("noise", -1, {}, "data.stress.level"),
    ("fast_motion", 1.5, {}, "data.stress.level"), ("dropped_frames", 1.0, {}, "data.stress.level"),
    ("noise", "high", {}, "data.stress.level"), ("noise", 1, {"sigma": 2}, "data.stress"),
    ("exposure", 1, {"direction": "sideways"}, "data.stress.direction"),
])  # fmt: skip
def test_bad_kind_level_or_option_is_a_config_error(kind, level, options, needle, room):
    with pytest.raises(ConfigError, match=needle.replace(".", r"\.")):
        apply_stress(room, kind, level, **options)


def test_config_node_wraps_the_sequence(tmp_path):
    cfg = compose(["+experiment=synthetic", "slam=known_poses", "data.n_frames=6", "data.width=32", "data.height=24",
                   "+data.stress={kind:fast_motion,level:1}"], output_dir=str(tmp_path))  # fmt: skip
    seq = make_sequence(cfg.data)
    assert isinstance(seq, StressedSequence) and len(seq) == 3 and seq.stress["kind"] == "fast_motion"
    bad = compose(["+experiment=synthetic", "slam=known_poses", "+data.stress={kind:noise,level:1,colour:red}"],
                  output_dir=str(tmp_path))
    with pytest.raises(ConfigError, match="data.stress"):
        make_sequence(bad.data)
