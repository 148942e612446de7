"""Shared data machinery: pose interpolation, Downscaled, factory, parser fuzzing."""
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from segs.data import Downscaled, build_sequence
from segs.data.euroc import read_calibration, read_groundtruth, read_image_index
from segs.data.files import read_rgb, read_timestamped_paths
from segs.data.poses import interpolate_poses, matrix_to_quat, poses_from_tq, quat_to_matrix, slerp
from segs.data.replica import read_traj
from segs.data.synthetic import SyntheticSequence
from segs.data.tum import TumSequence, read_tum_trajectory
from segs.errors import ConfigError, DataError

TUM_ROOT = Path(__file__).resolve().parents[1] / "datasets" / "tum_fr3_cabinet_kf"


def _rotz(deg):
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])


def test_quaternion_round_trip():
    rng = np.random.default_rng(1)
    q = rng.normal(size=(50, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    r = quat_to_matrix(q)
    np.testing.assert_allclose(quat_to_matrix(matrix_to_quat(r)), r, atol=1e-12)
    half_turn_z = np.array([[0, 0, np.sin(0.5), np.cos(0.5)]])  # 1 rad about z
    np.testing.assert_allclose(quat_to_matrix(half_turn_z)[0], _rotz(np.degrees(1.0)), atol=1e-12)


def test_slerp_is_constant_speed():
    q0, q1 = matrix_to_quat(_rotz(0)), matrix_to_quat(_rotz(90))
    for a in (0.0, 0.25, 0.5, 1.0):
        np.testing.assert_allclose(quat_to_matrix(slerp(q0, q1, np.array([a])))[0], _rotz(90 * a), atol=1e-12)
    flipped = slerp(q0, -q1, np.array([0.5]))  # q and -q are the same rotation
    np.testing.assert_allclose(quat_to_matrix(flipped)[0], _rotz(45), atol=1e-12)


def test_interpolation_rules():
    poses = np.stack([np.eye(4), np.eye(4)])
    poses[1, :3, :3], poses[1, :3, 3] = _rotz(40), [1.0, 2.0, 0.0]
    times = np.array([10.0, 10.08])
    out = interpolate_poses(times, poses, np.array([10.02, 10.0, 9.95, 9.85, 10.15, 10.3]), 0.1)
    np.testing.assert_allclose(out[0, :3, 3], [0.25, 0.5, 0.0])  # linear
    np.testing.assert_allclose(out[0, :3, :3], _rotz(10), atol=1e-12)  # SLERP
    np.testing.assert_allclose(out[1], poses[0])  # exact sample
    np.testing.assert_allclose(out[2], poses[0])  # before the first, within 0.1 s: nearest
    np.testing.assert_allclose(out[4], poses[1])  # after the last, within 0.1 s: nearest
    assert np.isnan(out[3]).all() and np.isnan(out[5]).all()  # farther: unknown
    # samples too far apart to interpolate: nearest within tolerance, else NaN
    far = interpolate_poses(np.array([0.0, 1.0]), poses, np.array([0.05, 0.5]), 0.1)
    np.testing.assert_allclose(far[0], poses[0])
    assert np.isnan(far[1]).all()
    single = interpolate_poses(np.array([1.0]), poses[:1], np.array([1.05, 2.0]), 0.1)
    np.testing.assert_allclose(single[0], np.eye(4))
    assert np.isnan(single[1]).all()


def test_downscaled_wrapper_is_consistent():
    full = SyntheticSequence(sensor="rgbd", n_frames=4, width=320, height=240)
    small = SyntheticSequence(sensor="rgbd", n_frames=4, width=160, height=120)
    half = Downscaled(full, 2)
    assert half.camera.fx == pytest.approx(small.camera.fx) and half.camera.cx == small.camera.cx
    assert (half.camera.width, half.camera.height) == (160, 120) and half.dropped == 0
    f, g = half[2], small[2]
    assert f.rgb.shape == (120, 160, 3) and f.depth.shape == (120, 160) and f.camera == half.camera
    assert np.median(np.abs(f.depth - g.depth)) < 0.01  # same geometry seen at half resolution
    assert np.abs(f.rgb - g.rgb).mean() < 0.1
    assert np.isin(f.depth, full[2].depth).all()  # nearest: depth values are never mixed
    same = Downscaled(full, 1)
    assert same.camera == full.camera and np.array_equal(same[1].rgb, full[1].rgb)
    stereo = Downscaled(SyntheticSequence(sensor="stereo", n_frames=2), 4)
    assert stereo[0].right.shape == (60, 80, 3) and stereo.camera.baseline == 0.1
    with pytest.raises(ConfigError):
        Downscaled(full, 0)


def test_build_sequence():
    seq = build_sequence("synthetic", sensor="mono", n_frames=3, downscale=2)
    assert isinstance(seq, Downscaled) and seq.camera.width == 160 and seq.sensor == "mono"
    tum = build_sequence("tum", TUM_ROOT, "mono", downscale=4)
    assert isinstance(tum, TumSequence) and tum.camera.width == 160
    with pytest.raises(ConfigError):
        build_sequence("nuscenes", "x", "mono")
    with pytest.raises(ConfigError):
        build_sequence("tum", None, "mono")


def test_read_rgb_rejects_float_images(tmp_path):
    import cv2
    path = tmp_path / "float.tiff"
    cv2.imwrite(str(path), np.zeros((4, 4), np.float32))
    with pytest.raises(DataError, match=r"float.tiff: expected an 8- or 16-bit image, got float32"):
        read_rgb(path)



@pytest.mark.parametrize("dtype, channels", [(np.uint8, 3), (np.uint8, 4), (np.uint16, 3), (np.uint8, 1),
                                             (np.uint16, 1)])
def test_read_rgb_values_and_channel_order(tmp_path, dtype, channels):
    """Every stored value v comes back as v / max in RGB order (BGR(A) files), grey replicated."""
    import cv2
    top = np.iinfo(dtype).max
    rng = np.random.default_rng(0)
    img = rng.integers(0, top + 1, (7, 9) if channels == 1 else (7, 9, channels), dtype=np.int64).astype(dtype)
    img.flat[:3] = (0, 1, top)
    path = tmp_path / "img.png"
    cv2.imwrite(str(path), img)
    out = read_rgb(path, (7, 9))
    assert out.dtype == np.float32 and out.shape == (7, 9, 3) and out.flags["C_CONTIGUOUS"]
    want = img.astype(np.float32) / np.float32(top)
    want = np.repeat(want[..., None], 3, axis=2) if channels == 1 else want[:, :, 2::-1]
    np.testing.assert_array_equal(out, want)

# --- fuzzing: random input is parsed or refused with DataError, never anything else -----------

TOKENS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-10**25, 10**25).map(str),
    st.text(alphabet="0123456789.-+eEnaif#, \t/_xyz", max_size=12),
    st.text(max_size=6),
)
LINES = st.lists(st.lists(TOKENS, max_size=18), max_size=6)
FUZZ = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


def _write(tmp_path, lines, sep=" ", name="index.txt"):
    path = tmp_path / name
    path.write_text("\n".join(sep.join(tokens) for tokens in lines), encoding="utf-8")
    return path


def _parses_or_data_error(func, *args):
    try:
        func(*args)
    except DataError as exc:
        assert "\n" not in str(exc)


@FUZZ
@given(lines=LINES)
def test_fuzz_tum_index_and_trajectory(tmp_path, lines):
    path = _write(tmp_path, lines)
    _parses_or_data_error(read_timestamped_paths, path)
    _parses_or_data_error(read_tum_trajectory, path)
    _parses_or_data_error(read_traj, path)


@FUZZ
@given(lines=LINES)
def test_fuzz_euroc_csv(tmp_path, lines):
    path = _write(tmp_path, lines, sep=",", name="data.csv")
    _parses_or_data_error(read_groundtruth, path)
    (tmp_path / "data").mkdir(exist_ok=True)
    _parses_or_data_error(read_image_index, tmp_path)


@FUZZ
@given(blob=st.binary(max_size=200))
def test_fuzz_binary_files(tmp_path, blob):
    path = tmp_path / "blob.txt"
    path.write_bytes(blob)
    _parses_or_data_error(read_timestamped_paths, path)
    _parses_or_data_error(read_calibration, path)


VALUES = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(-10**30, 10**30), st.floats(), st.text(max_size=8)),
    lambda inner: st.one_of(st.lists(inner, max_size=17),
                            st.dictionaries(st.sampled_from(["data", "rows", "cols"]), inner, max_size=3)),
    max_leaves=20,
)
GOOD = {"T_BS": {"cols": 4, "rows": 4, "data": np.eye(4).ravel().tolist()}, "resolution": [752, 480],
        "intrinsics": [458.0, 457.0, 367.0, 248.0], "distortion_coefficients": [-0.28, 0.07, 0.0, 0.0],
        "camera_model": "pinhole", "distortion_model": "radial-tangential"}


@FUZZ
@given(changes=st.dictionaries(st.sampled_from(sorted(GOOD)), VALUES, max_size=3),
       dropped=st.sets(st.sampled_from(sorted(GOOD)), max_size=2))
def test_fuzz_calibration_structure(tmp_path, changes, dropped):
    data = {k: v for k, v in {**GOOD, **changes}.items() if k not in dropped}
    path = tmp_path / "sensor.yaml"
    path.write_text("%YAML:1.0\n" + yaml.safe_dump(data), encoding="utf-8")
    _parses_or_data_error(read_calibration, path)


@FUZZ
@given(text=st.text(alphabet="%YAML:1.0[]{},-# \n\tT_BSdataintrinsics0123456789.e!&*|>'\"", max_size=120))
def test_fuzz_calibration_text(tmp_path, text):
    path = tmp_path / "sensor.yaml"
    path.write_text(text, encoding="utf-8")
    _parses_or_data_error(read_calibration, path)


def test_valid_calibration_parses(tmp_path):
    path = tmp_path / "sensor.yaml"
    path.write_text("%YAML:1.0\n" + yaml.safe_dump(GOOD))
    calib = read_calibration(path)
    assert calib.size == (752, 480) and calib.K[0, 0] == 458.0
    np.testing.assert_array_equal(calib.T_BS, np.eye(4))


def test_poses_from_tq_identity():
    np.testing.assert_array_equal(poses_from_tq(np.zeros((1, 3)), np.array([[0, 0, 0, 1.0]]))[0], np.eye(4))
