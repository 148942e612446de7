"""7-Scenes reader: generated native-layout folders, depth registration, and the real shared frames."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from segs.data.base import DepthRegistration
from segs.data.export import write_seven_scenes
from segs.data.frame import Camera
from segs.data.seven_scenes import COLOR_DISTORTION, COLOR_INTRINSICS, DEPTH_DISTORTION, DEPTH_TO_COLOR, SevenScenesSequence
from segs.data.synthetic import SyntheticSequence
from segs.data.tum import TumSequence
from segs.errors import ConfigError, DataError


@pytest.fixture(scope="module")
def synthetic():
    return SyntheticSequence(sensor="rgbd", n_frames=5, width=64, height=48)


def _identity(seq) -> dict:
    """Reader options that read a folder written by write_seven_scenes back unchanged."""
    c = seq.camera
    return {"intrinsics": [c.fx, c.fy, c.cx, c.cy], "depth_to_color": [0] * 6, "distortion": [0] * 4,
            "depth_distortion": [0] * 4}


def test_round_trip_of_a_sequence_folder(synthetic, tmp_path):
    root = write_seven_scenes(synthetic, tmp_path / "seq-01")
    seq = SevenScenesSequence(root, **_identity(synthetic))
    assert len(seq) == 5 and seq.sensor == "rgbd" and seq.name == "seq-01"
    np.testing.assert_allclose(seq.timestamps, np.arange(5) / 30)
    f, g = seq[3], synthetic[3]
    assert f.rgb.shape == (48, 64, 3) and np.abs(f.rgb - g.rgb).max() <= 0.5 / 255 + 1e-6
    assert np.abs(f.depth - g.depth).max() <= 0.5e-3 + 1e-6  # millimetres
    np.testing.assert_allclose(f.pose_c2w, g.pose_c2w, atol=1e-9)
    assert f.name == "frame-000003.color.png" and seq.lossless == {}
    mono = SevenScenesSequence(root, sensor="mono", **_identity(synthetic))
    assert mono[0].depth is None


def test_scene_folder_sequences_and_frame_range(synthetic, tmp_path):
    write_seven_scenes(synthetic, tmp_path / "scene" / "seq-01")
    write_seven_scenes(synthetic, tmp_path / "scene" / "seq-02", frames=[1, 2, 3], ext="jpg")
    with pytest.raises(ConfigError, match=r"data.sequence: .*scene holds several sequences \(seq-01, seq-02\)"):
        SevenScenesSequence(tmp_path / "scene")
    two = SevenScenesSequence(tmp_path / "scene", sequence=2, **_identity(synthetic))
    assert len(two) == 3 and two.name == "scene/seq-02" and two[0].name == "frame-000000.color.jpg"
    part = SevenScenesSequence(tmp_path / "scene", sequence="seq-01", frames=[2, 4], **_identity(synthetic))
    assert len(part) == 2 and part.frame_numbers.tolist() == [2, 3]
    np.testing.assert_allclose(part.timestamps, [2 / 30, 3 / 30])
    np.testing.assert_allclose(part[0].pose_c2w, synthetic[2].pose_c2w, atol=1e-9)


def test_invalid_depth_and_bad_input(synthetic, tmp_path):
    root = write_seven_scenes(synthetic, tmp_path / "seq")
    depth = cv2.imread(str(root / "frame-000001.depth.png"), cv2.IMREAD_UNCHANGED)
    depth[:5] = 65535  # 7-Scenes marks invalid depth with 65535 as well as 0
    cv2.imwrite(str(root / "frame-000001.depth.png"), depth)
    seq = SevenScenesSequence(root, **_identity(synthetic))
    assert (seq[1].depth[:5] == 0).all() and (seq[1].depth[5:] > 0).any()
    with pytest.raises(ConfigError, match=r"data.frames must be \[start, stop\)"):
        SevenScenesSequence(root, frames=[3, 1])
    with pytest.raises(DataError, match=r"no frame in data.frames"):
        SevenScenesSequence(root, frames=[10, 20])
    (root / "frame-000002.pose.txt").write_text("1 0 0 0\n0 2 0 0\n0 0 1 0\n0 0 0 1\n")
    with pytest.raises(DataError, match=r"frame-000002.pose.txt: pose: expected a rigid 4x4 transform"):
        SevenScenesSequence(root)
    (root / "frame-000002.pose.txt").write_text("1 0 0 0\n0 1 0 0\n")
    with pytest.raises(DataError, match=r"frame-000002.pose.txt: expected a 4x4 matrix"):
        SevenScenesSequence(root)
    (root / "frame-000003.depth.png").unlink()
    with pytest.raises(DataError, match=r"frame-000003.depth.png: depth image not found"):
        SevenScenesSequence(root)
    with pytest.raises(DataError, match=r"cannot provide sensor 'stereo'"):
        SevenScenesSequence(root, sensor="stereo")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match=r"empty: no frame-XXXXXX.color.png / .jpg images"):
        SevenScenesSequence(tmp_path / "empty")
    with pytest.raises(DataError, match=r"7-Scenes folder not found"):
        SevenScenesSequence(tmp_path / "nope")


def test_registration_moves_depth_into_the_colour_camera():
    """A depth step seen by a depth camera 5 cm to the left of the colour camera and with another
    focal length lands where the colour camera sees it; poses move by the same transform."""
    depth_cam = Camera(100.0, 100.0, 31.5, 23.5, 64, 48)
    color_cam = Camera(80.0, 80.0, 31.5, 23.5, 64, 48)
    depth = np.full((48, 64), 2.0, np.float32)
    depth[:, 32:] = 1.0  # a step at depth-camera x = 0 (the optical axis, u = 31.5 -> 32)
    reg = DepthRegistration([100, 100, 31.5, 23.5], [0, 0, 0, -0.05, 0, 0])
    out = reg.register(depth, color_cam)
    # colour x = depth x - 0.05, u = 31.5 + 80 x / z: the near side (z = 1) spans depth u 32..63,
    # x 0.005..0.315 -> colour u 27.9..52.7; the far side (z = 2) starts at depth u 0 -> colour 4.3
    row = out[24]
    near = np.flatnonzero(np.isclose(row, 1.0, atol=1e-4))
    far = np.flatnonzero(np.isclose(row, 2.0, atol=1e-4))
    assert (near.min(), near.max()) == (28, 53) and (far.min(), far.max()) == (4, 27)
    c2w_depth = np.eye(4)[None].repeat(2, 0)
    c2w_depth[1, :3, 3] = [1.0, 2.0, 3.0]
    c2w_color = reg.color_poses(c2w_depth)
    np.testing.assert_allclose(c2w_color[:, :3, 3], c2w_depth[:, :3, 3] + [0.05, 0, 0])
    assert DepthRegistration([100, 100, 31.5, 23.5]).register(depth, depth_cam) is depth  # same camera


def test_depth_lens_is_undistorted_before_the_registration():
    """A point seen through a depth lens (cv2.projectPoints with k1, k2) lands, after
    undistortion and registration into a pinhole colour camera 5 cm to the side, where the pinhole
    projects it; without the lens model it lands off by the distortion."""
    K = np.array([[100.0, 0, 63.5], [0, 100.0, 47.5], [0, 0, 1]])
    lens = np.array([-0.2, 0.05, 0.0, 0.0])
    point = np.array([[0.8, 0.6, 1.5]])  # depth camera, metres: near the image's corner (4 px of lens)
    (u, v), = cv2.projectPoints(point, np.zeros(3), np.zeros(3), K, lens)[0].reshape(1, 2)
    depth = np.zeros((96, 128), np.float32)
    depth[int(round(v)) - 1:int(round(v)) + 2, int(round(u)) - 1:int(round(u)) + 2] = 1.5
    color = Camera(100.0, 100.0, 63.5, 47.5, 128, 96)
    x, y, z = point[0] - [0.05, 0, 0]  # colour = depth - 5 cm in x
    want = np.array([63.5 + 100 * x / z, 47.5 + 100 * y / z])

    def landed(reg):
        rows, cols = np.nonzero(reg.register(depth, color))
        return np.array([cols.mean(), rows.mean()])

    assert np.abs(landed(DepthRegistration(K[[0, 1, 0, 1], [0, 1, 2, 2]], [0, 0, 0, -0.05, 0, 0],
                                           depth_distortion=lens)) - want).max() < 1.5
    assert np.abs(landed(DepthRegistration(K[[0, 1, 0, 1], [0, 1, 2, 2]], [0, 0, 0, -0.05, 0, 0])) - want).max() > 3.0
    with pytest.raises(ConfigError, match="data.depth_distortion"):
        DepthRegistration([100, 100, 31.5, 23.5], depth_distortion=[0.1])


# ------------------------------------------------------------------ the real shared frames
def test_native_and_tum_index_layouts_give_the_same_frames(seven_scenes_root):
    native = SevenScenesSequence(seven_scenes_root)
    tum = TumSequence(seven_scenes_root, intrinsics=list(COLOR_INTRINSICS), depth_scale=1000,
                      depth_intrinsics=[585, 585, 320, 240], depth_to_color=list(DEPTH_TO_COLOR),
                      distortion=list(COLOR_DISTORTION), depth_distortion=list(DEPTH_DISTORTION))
    assert len(native) == len(tum) == 600 and native.camera == tum.camera
    np.testing.assert_allclose(native.timestamps, tum.timestamps, atol=1e-6)
    np.testing.assert_allclose(native.gt_poses, tum.gt_poses, atol=1e-3)  # groundtruth.txt: 7 decimals
    for i in (0, 321, 599):
        a, b = native[i], tum[i]
        assert np.array_equal(a.rgb, b.rgb) and np.array_equal(a.depth, b.depth)


def test_lossless_reference_frames(seven_scenes_root):
    seq = SevenScenesSequence(seven_scenes_root, sensor="mono", frames=[140, 210])
    assert sorted(seq.lossless) == list(range(10, 60))  # frames 150-199 at positions 10-59
    jpeg, png = seq[15].rgb, seq.lossless_rgb(15)
    psnr = -10 * np.log10(np.mean((jpeg - png) ** 2))
    assert 33 < psnr < 40, psnr  # PROVENANCE: the JPEGs score about 36 dB against the PNGs
    assert seq.lossless_rgb(0) is None
    small = SevenScenesSequence(seven_scenes_root, sensor="mono", frames=[150, 152], downscale=2)
    assert small.lossless_rgb(0).shape == (240, 320, 3)


def _edge_agreement(seq, frames) -> float:
    """Mean colour-gradient magnitude under registered depth edges (relative to the image mean)."""
    scores = []
    for i in frames:
        f = seq[i]
        g = cv2.GaussianBlur(cv2.cvtColor((f.rgb * 255).astype(np.uint8), cv2.COLOR_RGB2GRAY).astype(np.float32), (5, 5), 1.5)
        ge = np.hypot(cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1))
        d = cv2.morphologyEx(f.depth, cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8))
        log_d = np.log(np.maximum(d, 0.1))
        de = np.hypot(cv2.Sobel(log_d, cv2.CV_32F, 1, 0), cv2.Sobel(log_d, cv2.CV_32F, 0, 1))
        de[cv2.erode((d > 0).astype(np.uint8), np.ones((5, 5), np.uint8)) == 0] = 0
        de = np.minimum(de, 0.3)
        scores.append(float((de * ge).sum() / de.sum() / ge.mean()))
    return float(np.mean(scores))


def test_calibrated_registration_aligns_depth_edges_with_colour_edges(seven_scenes_root):
    """The published 585 intrinsics with unregistered depth put depth edges 5-13 px off the colour
    edges; the measured colour calibration (reader default) lines them up better."""
    frames = range(0, 600, 60)
    calibrated = _edge_agreement(SevenScenesSequence(seven_scenes_root), frames)
    published = _edge_agreement(SevenScenesSequence(seven_scenes_root, intrinsics=[585, 585, 320, 240],
                                                     depth_to_color=[0] * 6), frames)
    assert calibrated > 1.08 * published, (calibrated, published)


def test_depth_and_colour_lenses_are_undistorted_alike(seven_scenes_root):
    """Depth edges agree with colour edges when both lenses are undistorted alike (the default) as
    well as with neither; undistorting the colour alone moves the colour edges off the depth's."""
    frames = range(0, 600, 60)
    default = _edge_agreement(SevenScenesSequence(seven_scenes_root), frames)
    pinholes = _edge_agreement(SevenScenesSequence(seven_scenes_root, distortion=[0] * 4, depth_distortion=[0] * 4),
                               frames)
    colour_only = _edge_agreement(SevenScenesSequence(seven_scenes_root, depth_distortion=[0] * 4), frames)
    assert default > 0.99 * pinholes and colour_only < 0.95 * default, (default, pinholes, colour_only)
    assert np.any(np.array(COLOR_DISTORTION) != 0) and COLOR_DISTORTION == DEPTH_DISTORTION


_FAULTS = """
import resource, sys, threading
from segs import process_settings
process_settings.apply()  # as segs's programs do
from segs.data.seven_scenes import SevenScenesSequence
seq = SevenScenesSequence(sys.argv[1])
seq[0]
def read():
    for i in range(1, 31):
        seq[i]
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
t = threading.Thread(target=read)
t.start()
t.join()
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


@pytest.mark.skipif(not __import__("sys").platform.startswith("linux"), reason="glibc's allocator settings")
def test_frames_read_in_a_thread_reuse_freed_memory(seven_scenes_root):
    """The process settings keep freed heap memory for the next frame (mallopt): reading real frames
    in a thread, as the frame source does, costs a fraction of the page faults it costs with glibc's
    defaults (SEGS_MALLOC=default), where each frame's large buffers are fresh mappings."""
    import os
    import subprocess
    import sys

    def faults(**env) -> int:
        out = subprocess.run([sys.executable, "-c", _FAULTS, str(seven_scenes_root)], capture_output=True, text=True,
                             env={**os.environ, **env}, check=True)
        return int(out.stdout.split()[-1])

    kept, default = faults(), faults(SEGS_MALLOC="default")
    assert kept < 0.3 * default, (kept, default)


def test_colour_distortion_undistorts_colour_only(synthetic, tmp_path):
    """data.distortion remaps the colour (and the lossless reference) to the pinhole of the same
    intrinsics, as cv2.undistort does; the depth and the poses stay; null is the measured lens."""
    root = write_seven_scenes(synthetic, tmp_path / "seq")
    plain = SevenScenesSequence(root, **_identity(synthetic))
    identity = {k: v for k, v in _identity(synthetic).items() if k != "distortion"}
    measured = SevenScenesSequence(root, **identity)  # null: the reader's COLOR_DISTORTION
    same = SevenScenesSequence(root, distortion=list(COLOR_DISTORTION), **identity)
    d = [-0.3, 0.1, 0.0, 0.0]
    lens = SevenScenesSequence(root, **{**_identity(synthetic), "distortion": d})
    f, g = lens[2], plain[2]
    np.testing.assert_array_equal(measured[2].rgb, same[2].rgb)
    assert np.abs(measured[2].rgb - g.rgb).max() > 0.05
    K, inner = plain.native_camera.K, (slice(8, -8), slice(8, -8))  # borders: the remaps' edges differ
    err = np.abs(f.rgb - cv2.undistort(g.rgb, K, np.array(d)))[inner].mean()
    wrong = np.abs(f.rgb - cv2.undistort(g.rgb, K, -np.array(d)))[inner].mean()
    assert err < 0.003 and wrong > 5 * err  # (cv2.undistort interpolates in fixed point)
    assert np.abs(f.rgb - g.rgb).max() > 0.05  # the lens moves the picture
    np.testing.assert_array_equal(f.depth, g.depth)
    np.testing.assert_allclose(f.pose_c2w, g.pose_c2w)
    with pytest.raises(ConfigError, match="data.distortion"):
        SevenScenesSequence(root, **{**_identity(synthetic), "distortion": [0.1, 0.2]})
