"""EuRoC MAV reader: real V1_01 stereo pairs (rectification, ground truth) and bad input."""
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from segs.data.euroc import EurocSequence, read_calibration
from segs.data.poses import quat_to_matrix
from segs.errors import ConfigError, DataError

ROOT = Path(__file__).resolve().parents[1] / "datasets" / "euroc_v101_micro"
MAV = ROOT / "mav0"


@pytest.fixture(scope="module")
def stereo():
    return EurocSequence(ROOT)


@pytest.fixture
def small(tmp_path):
    """A copy of the first 3 pairs (and 10 ground-truth rows) of the real sequence."""
    mav = tmp_path / "V1_01_small" / "mav0"
    for cam in ("cam0", "cam1"):
        (mav / cam / "data").mkdir(parents=True)
        shutil.copy(MAV / cam / "sensor.yaml", mav / cam)
        lines = (MAV / cam / "data.csv").read_text().splitlines()[:4]
        (mav / cam / "data.csv").write_text("\n".join(lines) + "\n")
        for line in lines[1:]:
            shutil.copy(MAV / cam / "data" / line.split(",")[1], mav / cam / "data")
    gt = mav / "state_groundtruth_estimate0"
    gt.mkdir()
    lines = (MAV / "state_groundtruth_estimate0" / "data.csv").read_text().splitlines()[:11]
    (gt / "data.csv").write_text("\n".join(lines) + "\n")
    return mav.parent


def _orb_pairs(frame):
    orb = cv2.ORB_create(2000)
    grey = [(img[..., 0] * 255).astype(np.uint8) for img in (frame.rgb, frame.right)]
    (k1, d1), (k2, d2) = (orb.detectAndCompute(g, None) for g in grey)
    matches = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(d1, d2)
    a = np.array([k1[m.queryIdx].pt for m in matches])
    b = np.array([k2[m.trainIdx].pt for m in matches])
    return a, b


def test_real_stereo_pairs_are_rectified(stereo):
    assert len(stereo) == 20 and stereo.sensor == "stereo" and stereo.dropped == 0
    cam = stereo.camera
    assert (cam.width, cam.height) == (752, 480) and 0.105 < cam.baseline < 0.115
    assert 400 < cam.fx < 470 and cam.fx == cam.fy
    for i in (0, 19):
        f = stereo[i]
        assert f.rgb.shape == f.right.shape == (480, 752, 3) and f.depth is None
        assert np.array_equal(f.rgb[..., 0], f.rgb[..., 2])  # grey replicated
        a, b = _orb_pairs(f)
        assert len(a) > 200
        assert np.median(np.abs(a[:, 1] - b[:, 1])) < 1.0  # horizontal epipolar lines
        assert np.median(a[:, 0] - b[:, 0]) > 0  # positive disparity
    np.testing.assert_allclose(stereo.timestamps[0], 1403715273.262142976)
    assert np.all(np.diff(stereo.timestamps) > 0.04)


def _first_gt_c2w():
    row = (MAV / "state_groundtruth_estimate0" / "data.csv").read_text().splitlines()[1].split(",")
    v = np.array(row[1:8], float)
    T_WB = np.eye(4)
    T_WB[:3, :3] = quat_to_matrix(v[[4, 5, 6, 3]][None])[0]
    T_WB[:3, 3] = v[:3]
    return T_WB @ read_calibration(MAV / "cam0" / "sensor.yaml").T_BS


def test_ground_truth_is_cam0_pose(stereo):
    mono = EurocSequence(ROOT, sensor="mono")
    np.testing.assert_allclose(mono[0].pose_c2w, _first_gt_c2w(), atol=1e-9)
    rect = stereo[0].pose_c2w
    np.testing.assert_allclose(rect[:3, 3], mono[0].pose_c2w[:3, 3])
    np.testing.assert_allclose(rect[:3, :3], mono[0].pose_c2w[:3, :3] @ stereo.rectify_rotation.T, atol=1e-12)
    assert np.isfinite(stereo.gt_poses).all()
    motion = np.linalg.norm(stereo.gt_poses[:, :3, 3] - stereo.gt_poses[0, :3, 3], axis=1)
    assert motion.max() < 0.01  # the vehicle is nearly still in this window


def test_mono_is_undistorted_left(small):
    seq = EurocSequence(small, sensor="mono")
    calib = read_calibration(small / "mav0" / "cam0" / "sensor.yaml")
    assert seq.camera.baseline is None and seq.camera.fx == calib.K[0, 0]
    f = seq[1]
    assert f.right is None
    raw = cv2.imread(str(seq.left_paths[1]), cv2.IMREAD_GRAYSCALE).astype(np.float32) / 255
    expected = cv2.undistort(raw, calib.K, calib.dist)
    assert np.abs(f.rgb[..., 0] - expected)[10:-10, 10:-10].mean() < 0.01
    assert np.abs(f.rgb[..., 0] - raw).mean() > 0.02


def test_mav0_folder_and_downscale(small):
    seq = EurocSequence(small / "mav0", downscale=2)
    assert seq.name == "V1_01_small" and len(seq) == 3
    full = EurocSequence(small)
    assert seq.camera == full.camera.scaled(2) and seq.camera.baseline == full.camera.baseline
    assert seq[0].right.shape == (240, 376, 3)


def test_sensor_modes_refused(small):
    with pytest.raises(DataError, match="rgbd") as err:
        EurocSequence(small, sensor="rgbd")
    assert str(small) in str(err.value)
    with pytest.raises(ConfigError):
        EurocSequence(small, sensor="depth")
    shutil.rmtree(small / "mav0" / "cam1")
    with pytest.raises(DataError, match="no cam1"):
        EurocSequence(small, sensor="stereo")
    assert len(EurocSequence(small, sensor="mono")) == 3


def test_unpaired_frames_dropped(small):
    csv = small / "mav0" / "cam1" / "data.csv"
    lines = csv.read_text().splitlines()
    csv.write_text("\n".join(lines[:2] + lines[3:]) + "\n")
    seq = EurocSequence(small)
    assert len(seq) == 2 and seq.dropped == 1
    csv.write_text(lines[0] + "\n1,x.png\n")
    with pytest.raises(DataError, match=r"cam1/data.csv:2: lists .*x.png"):
        EurocSequence(small)


def test_ground_truth_outside_range_is_nan(small):
    gt = small / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    lines = gt.read_text().splitlines()
    gt.write_text("\n".join(lines[:1] + lines[3:]) + "\n")  # starts after frames 0 and 1
    seq = EurocSequence(small, gt_max_difference=0.02)
    assert np.isnan(seq.gt_poses[0]).all() and seq[0].pose_c2w is None
    assert seq[2].pose_c2w is not None
    gt.unlink()
    assert EurocSequence(small).gt_poses is None


@pytest.mark.parametrize("edit,match", [
    (lambda ln: ln.replace(",0.069433,", ",0.569433,"), r"data.csv:2: quaternion norm"),
    (lambda ln: ln.replace(",0.878895,", ",nan,"), r"data.csv:2: expected a finite number"),
    (lambda ln: ln.split(",", 1)[1], r"data.csv:2: expected a non-negative timestamp in ns"),
    (lambda ln: ",".join(ln.split(",")[:5]), r"data.csv:2: expected 8 to 64 columns, got 5"),
])
def test_malformed_ground_truth(small, edit, match):
    gt = small / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    lines = gt.read_text().splitlines()
    gt.write_text("\n".join([lines[0], edit(lines[1])] + lines[2:]) + "\n")
    with pytest.raises(DataError, match=match):
        EurocSequence(small)


@pytest.mark.parametrize("old,new,match", [
    ("intrinsics: [458.654, 457.296, 367.215, 248.375]", "intrinsics: [458.654, 457.296]",
     r"'intrinsics' must be a list of 4 finite numbers"),
    ("intrinsics: [458.654, 457.296, 367.215, 248.375]", "", r"'intrinsics' must be a list of 4"),
    ("distortion_model: radial-tangential", "distortion_model: equidistant", r"equidistant.*not supported"),
    ("rate_hz: 20", "rate_hz: [20", r"cannot parse YAML"),
    ("0.0, 0.0, 0.0, 1.0]", "0.0, 0.0, 0.0, 2.0]", r"sensor.yaml: T_BS: expected a rigid 4x4 transform"),
    ("resolution: [752, 480]", "resolution: [752.5, 480]", r"integer resolution"),
])
def test_malformed_calibration(small, old, new, match):
    path = small / "mav0" / "cam0" / "sensor.yaml"
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new))
    with pytest.raises(DataError, match=match) as err:
        EurocSequence(small)
    assert "sensor.yaml" in str(err.value) and "\n" not in str(err.value)


@pytest.mark.parametrize("line,match", [
    ("abc,1.png", r"cam0/data.csv:5: expected a non-negative timestamp in ns, got 'abc'"),
    ("1403715273312143104,1.png", r"cam0/data.csv:5: decreasing timestamp"),
    ("1,2,3", r"cam0/data.csv:5: expected 2 columns, got 3"),
])
def test_malformed_image_index(small, line, match):
    with open(small / "mav0" / "cam0" / "data.csv", "a") as fh:
        fh.write(line + "\n")
    with pytest.raises(DataError, match=match):
        EurocSequence(small)


def test_missing_folders(tmp_path, small):
    with pytest.raises(DataError, match="not found"):
        EurocSequence(tmp_path / "nothing")
    shutil.rmtree(small / "mav0" / "cam0")
    with pytest.raises(DataError, match=r"cam0: EuRoC cam0 folder not found"):
        EurocSequence(small)
