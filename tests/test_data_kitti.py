"""KITTI odometry reader: a generated folder of the benchmark's layout, bad input, the real frames."""
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from segs.data import build_sequence
from segs.data.kitti import KittiSequence
from segs.errors import ConfigError, DataError

FX, CX, CY, BASELINE = 70.0, 31.5, 15.5, 0.54
COLOR_OFFSET = -0.06  # x of the colour cameras' centre in camera 0's frame (KITTI: about -6 cm)


def _matrix_line(name: str, P: np.ndarray) -> str:
    return f"{name}: " + " ".join(f"{v:.12e}" for v in P.ravel())


def _projection(x_centre: float) -> np.ndarray:
    K = np.array([[FX, 0, CX], [0, FX, CY], [0, 0, 1.0]])
    return K @ np.c_[np.eye(3), [-x_centre, 0, 0]]


def _poses(n: int) -> np.ndarray:
    """c2w [n,4,4]: forward 1 m per frame with a slow yaw."""
    out = np.tile(np.eye(4), (n, 1, 1))
    for i in range(n):
        a = 0.02 * i
        out[i, :3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
        out[i, :3, 3] = [0.1 * i, 0.0, 1.0 * i]
    return out


def write_kitti(folder: Path, n: int = 4, folders=("image_0", "image_1", "image_2", "image_3"),
                poses_name: str | None = "poses.txt") -> Path:
    """A KITTI odometry sequence folder of n 64x32 frames: frame i, image k has value 10 i + k."""
    folder.mkdir(parents=True)
    for k, name in enumerate(folders):
        (folder / name).mkdir()
        for i in range(n):
            shape = (32, 64, 3) if name in ("image_2", "image_3") else (32, 64)
            cv2.imwrite(str(folder / name / f"{i:06d}.png"), np.full(shape, 10 * i + k, np.uint8))
    lines = [_matrix_line(f"P{k}", _projection(x)) for k, x in
             enumerate((0.0, BASELINE, COLOR_OFFSET, COLOR_OFFSET + BASELINE))]
    (folder / "calib.txt").write_text("\n".join(lines + ["Tr: " + " ".join(["0"] * 12)]) + "\n")
    (folder / "times.txt").write_text("".join(f"{0.1 * i:.6e}\n" for i in range(n)))
    if poses_name:
        (folder / poses_name).write_text("".join(" ".join(f"{v:.9e}" for v in T[:3].ravel()) + "\n"
                                                 for T in _poses(n)))
    return folder


@pytest.fixture
def kitti(tmp_path):
    return write_kitti(tmp_path / "07")


def test_mono_reads_the_left_grey_camera(kitti):
    seq = KittiSequence(kitti)
    assert len(seq) == 4 and seq.sensor == "mono" and seq.name == "07"
    cam = seq.camera
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height, cam.baseline) == (FX, FX, CX, CY, 64, 32, None)
    np.testing.assert_allclose(seq.timestamps, [0, 0.1, 0.2, 0.3])
    f = seq[2]
    assert f.rgb.shape == (32, 64, 3) and f.right is None and f.depth is None and f.name == "000002.png"
    np.testing.assert_allclose(f.rgb, 20 / 255, atol=1e-6)
    np.testing.assert_allclose(f.pose_c2w, _poses(4)[2], atol=1e-8)


def test_stereo_pair_and_baseline_from_calib(kitti):
    seq = KittiSequence(kitti, sensor="stereo")
    assert seq.camera.baseline == pytest.approx(BASELINE)
    f = seq[1]
    np.testing.assert_allclose(f.rgb, 10 / 255, atol=1e-6)
    np.testing.assert_allclose(f.right, 11 / 255, atol=1e-6)


def test_colour_cameras_and_their_ground_truth(kitti):
    seq = KittiSequence(kitti, sensor="stereo", color=True)
    f = seq[3]
    np.testing.assert_allclose(f.rgb, 32 / 255, atol=1e-6)
    np.testing.assert_allclose(f.right, 33 / 255, atol=1e-6)
    assert seq.camera.baseline == pytest.approx(BASELINE)
    # the colour camera's centre is COLOR_OFFSET along camera 0's x axis
    expected = _poses(4)[3] @ np.array([COLOR_OFFSET, 0, 0, 1.0])
    np.testing.assert_allclose(f.pose_c2w[:3, 3], expected[:3], atol=1e-8)


def test_frame_range_downscale_and_factory(kitti):
    seq = build_sequence("kitti", kitti, sensor="mono", frames=[1, 3], downscale=2)
    assert len(seq) == 2 and (seq.camera.width, seq.camera.height) == (32, 16)
    assert seq.camera.fx == pytest.approx(FX / 2)
    np.testing.assert_allclose(seq.timestamps, [0.1, 0.2])
    np.testing.assert_allclose(seq[0].pose_c2w, _poses(4)[1], atol=1e-8)
    assert seq[1].rgb.shape == (16, 32, 3)


def test_benchmark_layout_poses_beside_sequences(tmp_path):
    root = write_kitti(tmp_path / "dataset" / "sequences" / "05", poses_name=None)
    assert KittiSequence(root).gt_poses is None
    (tmp_path / "dataset" / "poses").mkdir()
    write_kitti(tmp_path / "tmp", poses_name="poses.txt")
    (tmp_path / "tmp" / "poses.txt").rename(tmp_path / "dataset" / "poses" / "05.txt")
    np.testing.assert_allclose(KittiSequence(root).gt_poses, _poses(4), atol=1e-8)


def test_sensors_the_folder_cannot_provide(tmp_path):
    mono_only = write_kitti(tmp_path / "m", folders=("image_0",))
    with pytest.raises(DataError, match=r"cannot provide sensor 'stereo': no image_1 folder \(available: mono\)"):
        KittiSequence(mono_only, sensor="stereo")
    with pytest.raises(DataError, match="KITTI has no depth camera"):
        KittiSequence(mono_only, sensor="rgbd")
    with pytest.raises(DataError, match="image_2 folder not found"):
        KittiSequence(mono_only, color=True)
    with pytest.raises(ConfigError, match="sensor must be one of"):
        KittiSequence(mono_only, sensor="lidar")


def _edit(path: Path, lineno: int, text: str | None) -> None:
    lines = path.read_text().splitlines()
    if text is None:
        del lines[lineno - 1]
    else:
        lines[lineno - 1] = text
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize("file,lineno,text,message", [
    ("calib.txt", 1, "P0: 1 2 3", r"calib.txt:1: P0 has 3 numbers, expected 12"),
    ("calib.txt", 1, "P0 1 0 0 0 0 1 0 0 0 0 1 0", r"calib.txt:1: expected 'NAME: 12 numbers'"),
    ("calib.txt", 1, "P0: 1 0 0 0 0 1 0 0 0 0 x 0", r"calib.txt:1: expected a finite number, got 'x'"),
    ("calib.txt", 1, "P0: -70 0 31 0 0 70 15 0 0 0 1 0", r"calib.txt: P0 is not a rectified pinhole projection"),
    ("calib.txt", 1, None, r"calib.txt: no 'P0:' line"),
    ("times.txt", 3, "0.05", r"times.txt:3: decreasing timestamp"),
    ("times.txt", 2, "0.1 0.2", r"times.txt:2: expected 1 columns, got 2"),
    ("poses.txt", 2, None, r"poses.txt: 3 poses for 4 frames in times.txt"),
    ("poses.txt", 2, "2 0 0 0 0 1 0 0 0 0 1 0", r"poses.txt:2: expected a rigid 4x4 transform"),
    ("poses.txt", 3, "1 0 0 0 0 1 0 0 0 0 1 nan", r"poses.txt:3: expected a finite number, got 'nan'"),
])  # fmt: skip
def test_bad_files_are_one_line_errors_naming_the_file(kitti, file, lineno, text, message):
    _edit(kitti / file, lineno, text)
    with pytest.raises(DataError, match=message) as err:
        KittiSequence(kitti)
    assert "\n" not in str(err.value)


def test_missing_files_and_images(kitti, tmp_path):
    with pytest.raises(DataError, match="KITTI sequence folder not found"):
        KittiSequence(tmp_path / "nope")
    (kitti / "image_0" / "000003.png").unlink()
    with pytest.raises(DataError, match=r"image_0/000003.png: image not found \(times.txt lists 4 frames\)"):
        KittiSequence(kitti)
    assert len(KittiSequence(kitti, frames=[0, 3])) == 3
    (kitti / "image_0" / "000001.png").write_bytes(b"not a png")
    with pytest.raises(DataError, match=r"000001.png: cannot read image"):
        KittiSequence(kitti, frames=[0, 3])[1]
    (kitti / "times.txt").unlink()
    with pytest.raises(DataError, match=r"times.txt: file not found"):
        KittiSequence(kitti)


def test_stereo_right_camera_must_match_the_left(kitti):
    lines = (kitti / "calib.txt").read_text().splitlines()
    lines[1] = _matrix_line("P1", _projection(-BASELINE))  # right camera to the left
    (kitti / "calib.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match=r"calib.txt: P1 is not the right camera of a rectified pair with P0"):
        KittiSequence(kitti, sensor="stereo")
    assert KittiSequence(kitti).camera.baseline is None  # mono does not read P1


def test_stereo_experiment_refuses_a_left_only_folder_in_one_line(tmp_path):
    root = write_kitti(tmp_path / "left_only", n=2, folders=("image_0",))
    run = subprocess.run([sys.executable, "-m", "segs.track", "+experiment=kitti_stereo", f"data.root={root}",
                          f"hydra.run.dir={tmp_path / 'run'}"], capture_output=True, text=True, timeout=120)
    assert run.returncode == 2
    lines = [line for line in run.stderr.splitlines() if line.strip()]
    assert lines == [f"error: {root}: cannot provide sensor 'stereo': no image_1 folder (available: mono)"]


def test_real_kitti_frames(kitti_root):
    seq = KittiSequence(kitti_root)
    assert len(seq) == 51 and seq.sensor == "mono"
    cam = seq.camera
    assert (cam.width, cam.height) == (1241, 376) and cam.fx == pytest.approx(718.856)
    assert cam.cx == pytest.approx(607.1928) and cam.cy == pytest.approx(185.2157)
    steps = np.linalg.norm(np.diff(seq.gt_poses[:, :3, 3], axis=0), axis=1)
    assert steps.sum() == pytest.approx(51.76, abs=0.01) and 0.9 < steps.min() and steps.max() < 1.3
    np.testing.assert_allclose(seq.gt_poses[0], np.eye(4), atol=1e-6)
    f = seq[50]
    assert f.rgb.shape == (376, 1241, 3) and np.array_equal(f.rgb[..., 0], f.rgb[..., 2])
    assert 0.1 < f.rgb.mean() < 0.9
    with pytest.raises(DataError, match="no image_1 folder"):
        KittiSequence(kitti_root, sensor="stereo")
