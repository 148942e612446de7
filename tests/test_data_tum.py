"""TUM RGB-D reader: real keyframes, generated folders, association and bad input."""
from pathlib import Path

import cv2
import numpy as np
import pytest

from segs.data.export import write_tum
from segs.data.synthetic import SyntheticSequence
from segs.data.tum import FREIBURG, TumSequence, associate, freiburg_of
from segs.errors import ConfigError, DataError

ROOT = Path(__file__).resolve().parents[1] / "datasets" / "tum_fr3_cabinet_kf"


@pytest.fixture(scope="module")
def cabinet():
    return TumSequence(ROOT)


@pytest.fixture(scope="module")
def synthetic():
    return SyntheticSequence(sensor="rgbd", n_frames=6, width=64, height=48)


@pytest.fixture
def folder(tmp_path, synthetic):
    """A valid generated TUM folder (named fr3) of 6 frames at 64x48."""
    return write_tum(synthetic, tmp_path / "rgbd_dataset_freiburg3_synth", time_offset=1000.0)


def _edit(path: Path, old: str, new: str) -> None:
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new, 1))


def _data_lines(path: Path) -> list[str]:
    return [ln for ln in path.read_text().splitlines() if not ln.startswith("#")]


def test_real_cabinet_frames(cabinet):
    assert len(cabinet) == 58 and cabinet.sensor == "rgbd" and cabinet.dropped == 0
    cam = cabinet.camera
    assert (cam.width, cam.height) == (640, 480)
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == FREIBURG[3][0]
    f = cabinet[0]
    assert f.rgb.shape == (480, 640, 3) and f.rgb.dtype == np.float32 and f.rgb.max() <= 1
    assert f.depth.shape == (480, 640) and f.depth.dtype == np.float32
    assert 0.8 < (f.depth > 0).mean() < 0.92 and 0.3 < np.median(f.depth[f.depth > 0]) < 5
    assert f.name == "rgb/0000_rgb_raw.jpg" and f.right is None
    assert np.all(np.diff(cabinet.timestamps) > 0) and f.timestamp == cabinet.timestamps[0]
    assert cabinet.gt_poses.shape == (58, 4, 4) and np.isfinite(cabinet.gt_poses).all()
    np.testing.assert_allclose(f.pose_c2w[:3, 3], [-2.5508, 0.9872, 1.1019])


def test_real_cabinet_depth_and_poses_agree(cabinet):
    """Depth of frame 10 moved by the c2w ground truth lands on the depth of frame 11."""
    a, b = cabinet[10], cabinet[11]
    cam = cabinet.camera
    v, u = np.nonzero(a.depth > 0)
    z = a.depth[v, u]
    pts = np.stack([(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z, np.ones_like(z)])
    q = np.linalg.inv(b.pose_c2w) @ a.pose_c2w @ pts
    ub = np.round(cam.fx * q[0] / q[2] + cam.cx).astype(int)
    vb = np.round(cam.fy * q[1] / q[2] + cam.cy).astype(int)
    ok = (q[2] > 0) & (ub >= 0) & (vb >= 0) & (ub < cam.width) & (vb < cam.height)
    zb = b.depth[vb[ok], ub[ok]]
    residual = np.abs(zb - q[2][ok])[zb > 0]
    assert len(residual) > 10000 and np.median(residual) < 0.03


def test_mono_needs_no_depth(tmp_path, folder):
    (folder / "depth.txt").unlink()
    seq = TumSequence(folder, sensor="mono")
    assert len(seq) == 6 and seq[0].depth is None and seq.sensor == "mono"
    with pytest.raises(DataError, match="depth.txt") as err:
        TumSequence(folder, sensor="rgbd")
    assert str(folder) in str(err.value)


def test_stereo_and_unknown_sensor_refused(folder):
    with pytest.raises(DataError, match="stereo") as err:
        TumSequence(folder, sensor="stereo")
    assert str(folder) in str(err.value) and "\n" not in str(err.value)
    with pytest.raises(ConfigError):
        TumSequence(folder, sensor="lidar")


def test_generated_folder_round_trip(folder, synthetic):
    seq = TumSequence(folder, intrinsics=[synthetic.camera.fx, synthetic.camera.fy,
                                          synthetic.camera.cx, synthetic.camera.cy])
    assert len(seq) == 6 and seq.timestamps[0] == pytest.approx(1000.0)
    for i in (0, 5):
        f, g = seq[i], synthetic[i]
        assert np.abs(f.rgb - g.rgb).max() <= 0.5 / 255 + 1e-6
        assert np.abs(f.depth - g.depth).max() <= 0.5 / 5000 + 1e-6
        np.testing.assert_allclose(f.pose_c2w, g.pose_c2w, atol=1e-6)


def test_grey_images_and_comments(folder):
    path = folder / "rgb" / "000002.png"
    cv2.imwrite(str(path), cv2.imread(str(path), cv2.IMREAD_GRAYSCALE))
    _edit(folder / "rgb.txt", "# timestamp", "# a comment\n\n# timestamp")
    f = TumSequence(folder)[2]
    assert f.rgb.shape == (48, 64, 3) and np.array_equal(f.rgb[..., 0], f.rgb[..., 2])


def test_association_drops_unmatched_frames(folder):
    lines = _data_lines(folder / "depth.txt")
    t, name = lines[2].split()
    _edit(folder / "depth.txt", lines[2], f"{float(t) + 0.025:.6f} {name}")
    seq = TumSequence(folder)
    assert len(seq) == 5 and seq.dropped == 1 and 1000 + 2 / 30 not in seq.timestamps
    assert len(TumSequence(folder, sensor="mono")) == 6


def test_association_fails_when_nothing_pairs(folder):
    rows = [ln.split() for ln in _data_lines(folder / "depth.txt")]
    text = "".join(f"{float(t) + 0.5:.6f} {name}\n" for t, name in rows)
    (folder / "depth.txt").write_text(text)
    with pytest.raises(DataError, match="depth.txt.*0.02 s"):
        TumSequence(folder)


def test_associate_rule():
    rgb = np.array([0.0, 0.033, 0.066, 0.1, 0.2])
    depth = np.array([0.005, 0.03, 0.031, 0.09, 0.25])
    i, j = associate(rgb, depth, 0.02)
    assert list(zip(i, j)) == [(0, 0), (1, 2), (3, 3)]  # closest first, each used once, < 0.02
    i, j = associate(rgb, np.zeros(0), 0.02)
    assert len(i) == 0


def test_ground_truth_interpolated_and_nan_outside(folder, synthetic):
    gt = folder / "groundtruth.txt"
    lines = _data_lines(gt)
    gt.write_text("\n".join(lines[:2] + lines[3:4]) + "\n")  # frames 0, 1, 3 of 6 (1/30 s apart)
    seq = TumSequence(folder, intrinsics=[50, 50, 31.5, 23.5], gt_max_difference=0.05)
    np.testing.assert_allclose(seq.gt_poses[4], synthetic.gt_poses[3], atol=1e-6)  # nearest, 0.033 s away
    assert np.isnan(seq.gt_poses[5]).all() and seq[5].pose_c2w is None  # 0.067 s away
    p0, p1, p2 = synthetic.gt_poses[1], synthetic.gt_poses[3], seq.gt_poses[2]
    np.testing.assert_allclose(p2[:3, 3], (p0[:3, 3] + p1[:3, 3]) / 2, atol=1e-4)  # 1e-6 s stamps
    angle = lambda r: np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1)))  # noqa: E731
    a01 = angle(p0[:3, :3].T @ p1[:3, :3])
    assert angle(p0[:3, :3].T @ p2[:3, :3]) == pytest.approx(a01 / 2, rel=1e-3)


@pytest.mark.parametrize("name,expected", [("rgbd_dataset_freiburg1_xyz", 1), ("fr2_desk", 2),
                                           ("tum_fr3_cabinet_kf", 3), ("my_room", None), ("fr12", None)])
def test_freiburg_from_folder_name(tmp_path, name, expected):
    assert freiburg_of(tmp_path / name) == expected


def test_freiburg1_images_are_undistorted(tmp_path, synthetic):
    folder = write_tum(synthetic, tmp_path / "rgbd_dataset_freiburg1_synth", frames=[0])
    seq = TumSequence(folder)
    k, d = FREIBURG[1]
    assert (seq.camera.fx, seq.camera.cy) == (k[0], k[3])
    raw = cv2.imread(str(folder / "rgb" / "000000.png"))[:, :, ::-1].astype(np.float32) / 255
    expected = cv2.undistort(raw, seq.camera.K, np.array(d))
    assert np.abs(seq[0].rgb - expected)[8:-8, 8:-8].mean() < 0.01
    assert not np.allclose(seq[0].rgb, raw)
    plain = TumSequence(folder, distortion=[0, 0, 0, 0])
    np.testing.assert_allclose(plain[0].rgb, raw)


def test_depth_registered_by_the_reader_is_not_undistorted_again(tmp_path, synthetic):
    """Depth from a separate depth camera is registered into the colour camera's pinhole, so the
    colour lens's undistortion, which the colour image gets, must not move it again; the depth
    lens (depth_distortion) is undone before the registration."""
    folder = write_tum(synthetic, tmp_path / "rgbd_dataset_freiburg1_synth", frames=[0])
    c = TumSequence(folder).camera
    same_camera = {"depth_intrinsics": [c.fx, c.fy, c.cx, c.cy], "depth_to_color": [0] * 6}
    lens, plain = TumSequence(folder, **same_camera), TumSequence(folder, distortion=[0] * 4, **same_camera)
    assert np.abs(lens[0].rgb - plain[0].rgb).max() > 0.05  # the colour lens (freiburg1) is undone
    np.testing.assert_array_equal(lens[0].depth, plain[0].depth)  # the depth, registered, is not
    d = [-0.2, 0.0, 0.0, 0.0]
    K = np.array([[c.fx, 0, c.cx], [0, c.fy, c.cy], [0, 0, 1.0]])
    maps = cv2.initUndistortRectifyMap(K, np.array(d), None, K, (c.width, c.height), cv2.CV_32FC1)
    want = cv2.remap(plain[0].depth, *maps, cv2.INTER_NEAREST)
    np.testing.assert_array_equal(TumSequence(folder, depth_distortion=d, **same_camera)[0].depth, want)
    with pytest.raises(ConfigError, match="depth_intrinsics"):
        TumSequence(folder, depth_distortion=d)


def test_unknown_camera_needs_intrinsics(tmp_path, synthetic):
    folder = write_tum(synthetic, tmp_path / "my_room", frames=[0, 1])
    with pytest.raises(DataError, match="freiburg"):
        TumSequence(folder)
    assert TumSequence(folder, freiburg=2).camera.fx == 520.9
    with pytest.raises(ConfigError):
        TumSequence(folder, freiburg=4)
    assert TumSequence(folder, intrinsics=[100, 101, 30, 20]).camera.fy == 101
    with pytest.raises(ConfigError):
        TumSequence(folder, intrinsics=[100, 101, 30])
    with pytest.raises(ConfigError):
        TumSequence(folder, intrinsics=[-1, 101, 30, 20])


def test_downscale(folder):
    full, half = TumSequence(folder), TumSequence(folder, downscale=2)
    assert half.camera == full.camera.scaled(2) and (half.camera.width, half.camera.height) == (32, 24)
    f, h = full[1], half[1]
    assert h.rgb.shape == (24, 32, 3) and h.depth.shape == (24, 32) and h.camera == half.camera
    assert np.isin(h.depth, f.depth).all()  # nearest: no mixed depths
    assert abs(h.rgb.mean() - f.rgb.mean()) < 0.01
    with pytest.raises(ConfigError):
        TumSequence(folder, downscale=0.5)


# --- malformed input: each a one-line DataError naming the file ----------------------------

def _raises(folder, match, **kwargs):
    with pytest.raises(DataError, match=match) as err:
        seq = TumSequence(folder, **kwargs)
        for i in range(len(seq)):
            seq[i]
    assert "\n" not in str(err.value)
    return str(err.value)


def test_missing_folder_and_index(tmp_path, folder):
    assert str(tmp_path / "nope") in _raises(tmp_path / "nope", "not found")
    (folder / "rgb.txt").unlink()
    _raises(folder, r"rgb.txt: file not found")


def test_index_names_missing_image(folder):
    (folder / "rgb" / "000003.png").unlink()
    _raises(folder, r"rgb.txt:6: lists .*000003.png, which does not exist")


def test_corrupt_and_wrong_type_images(folder):
    (folder / "rgb" / "000001.png").write_bytes(b"\x89PNG garbage")
    _raises(folder, r"000001.png: cannot read image")
    cv2.imwrite(str(folder / "rgb" / "000001.png"), np.zeros((48, 64, 3), np.uint8))
    cv2.imwrite(str(folder / "depth" / "000004.png"), np.zeros((48, 64), np.uint8))
    _raises(folder, r"depth/000004.png: expected a 16-bit single-channel depth")


def test_depth_of_another_size(folder):
    cv2.imwrite(str(folder / "depth" / "000002.png"), np.zeros((24, 32), np.uint16))
    msg = _raises(folder, r"depth/000002.png: depth image is 32x24, expected 64x48")
    assert "colour image" in msg


def test_rgb_of_another_size(folder):
    cv2.imwrite(str(folder / "rgb" / "000004.png"), np.zeros((24, 32, 3), np.uint8))
    _raises(folder, r"rgb/000004.png: image is 32x24, expected 64x48")


def test_empty_index(folder):
    (folder / "rgb.txt").write_text("# nothing\n")
    _raises(folder, "rgb.txt: no images listed")


@pytest.mark.parametrize("line,match", [
    ("1000.5 rgb/000000.png extra", r"rgb.txt:9: expected 2 columns, got 3"),
    ("abc rgb/000000.png", r"rgb.txt:9: expected a finite timestamp, got 'abc'"),
    ("nan rgb/000000.png", r"rgb.txt:9: expected a finite timestamp"),
    ("1000.1 rgb/000000.png", r"rgb.txt:9: decreasing timestamp"),
    ("1000.166667 rgb/000000.png", r"rgb.txt:9: duplicate timestamp"),
])
def test_malformed_index_lines(folder, line, match):
    with open(folder / "rgb.txt", "a") as fh:
        fh.write(line + "\n")
    _raises(folder, match, sensor="mono")


@pytest.mark.parametrize("edit,match", [
    (lambda ln: ln.rsplit(" ", 1)[0] + " 2.0", r"groundtruth.txt:4: quaternion norm"),
    (lambda ln: ln.replace(ln.split()[1], "nan", 1),
     r"groundtruth.txt:4: expected a finite number, got 'nan'"),
    (lambda ln: ln + " 7", r"groundtruth.txt:4: expected 8 columns, got 9"),
    (lambda ln: "999 " + ln.split(" ", 1)[1], r"groundtruth.txt:4: decreasing timestamp"),
])
def test_malformed_ground_truth(folder, edit, match):
    gt = folder / "groundtruth.txt"
    line = _data_lines(gt)[1]  # file line 4 (two header lines)
    _edit(gt, line, edit(line))
    _raises(folder, match)
