"""Replica (NICE-SLAM layout) reader on tiny generated folders."""
import cv2
import numpy as np
import pytest

from segs.data.export import write_replica
from segs.data.replica import ReplicaSequence
from segs.data.synthetic import SyntheticSequence
from segs.errors import ConfigError, DataError


@pytest.fixture(scope="module")
def full_size(tmp_path_factory):
    """3 synthetic frames at Replica's 1200x680 with fx = fy = 600 (90 degree field of view)."""
    syn = SyntheticSequence(sensor="rgbd", n_frames=3, width=1200, height=680, fov_deg=90.0)
    return syn, write_replica(syn, tmp_path_factory.mktemp("replica") / "room0")


@pytest.fixture
def small(tmp_path):
    syn = SyntheticSequence(sensor="rgbd", n_frames=4, width=40, height=30)
    return write_replica(syn, tmp_path / "office0", ext="png")


K_SMALL = [28.6, 28.6, 19.5, 14.5]


def test_full_size_defaults_match_the_generator(full_size):
    syn, root = full_size
    seq = ReplicaSequence(root)
    assert len(seq) == 3 and seq.name == "room0" and seq.sensor == "rgbd" and seq.dropped == 0
    cam = seq.camera
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height) == (600, 600, 599.5, 339.5, 1200, 680)
    assert syn.camera.fx == pytest.approx(600.0)
    np.testing.assert_allclose(seq.timestamps, [0, 1 / 30, 2 / 30])
    f, g = seq[1], syn[1]
    assert f.rgb.shape == (680, 1200, 3) and f.depth.shape == (680, 1200)
    assert np.abs(f.depth - g.depth).max() <= 0.5 / 6553.5 + 1e-6
    assert np.abs(f.rgb - g.rgb).mean() < 0.02  # JPEG
    np.testing.assert_allclose(f.pose_c2w, g.pose_c2w, atol=1e-9)
    assert f.name == "frame000001.jpg"


def test_mono_downscale_fps(full_size):
    syn, root = full_size
    seq = ReplicaSequence(root, sensor="mono", downscale=4, fps=10)
    f = seq[2]
    assert f.depth is None and f.rgb.shape == (170, 300, 3)
    assert seq.camera == ReplicaSequence(root).camera.scaled(4) and seq.camera.cx == 149.5
    assert f.timestamp == pytest.approx(0.2)


def test_other_sizes_need_intrinsics(small):
    with pytest.raises(DataError, match=r"frame000000.png: image is 40x30, expected 1200x680"):
        ReplicaSequence(small)
    seq = ReplicaSequence(small, intrinsics=K_SMALL)
    assert seq.camera.fx == 28.6 and seq[3].depth.shape == (30, 40)


def test_stereo_refused(small):
    with pytest.raises(DataError, match="stereo") as err:
        ReplicaSequence(small, sensor="stereo", intrinsics=K_SMALL)
    assert str(small) in str(err.value)
    with pytest.raises(ConfigError):
        ReplicaSequence(small, intrinsics=K_SMALL, fps=0)


def test_missing_pieces(tmp_path, small):
    with pytest.raises(DataError, match="not found"):
        ReplicaSequence(tmp_path / "absent")
    (small / "results" / "depth000002.png").unlink()
    with pytest.raises(DataError, match=r"depth000002.png: depth image not found"):
        ReplicaSequence(small, intrinsics=K_SMALL)
    assert len(ReplicaSequence(small, sensor="mono", intrinsics=K_SMALL)) == 4
    for p in (small / "results").glob("frame*"):
        p.unlink()
    with pytest.raises(DataError, match=r"results: no frame\*.jpg images"):
        ReplicaSequence(small, intrinsics=K_SMALL)


def test_trajectory_checks(small):
    traj = small / "traj.txt"
    lines = traj.read_text().splitlines()
    traj.write_text("\n".join(lines[:3]) + "\n")
    with pytest.raises(DataError, match=r"traj.txt: 3 poses for 4 frames"):
        ReplicaSequence(small, intrinsics=K_SMALL)
    traj.write_text("\n".join(lines[:2] + [lines[2] + " 1"] + lines[3:]) + "\n")
    with pytest.raises(DataError, match=r"traj.txt:3: expected 16 columns, got 17"):
        ReplicaSequence(small, intrinsics=K_SMALL)
    scaled = " ".join(str(2 * float(v)) for v in lines[1].split())
    traj.write_text("\n".join([lines[0], scaled] + lines[2:]) + "\n")
    with pytest.raises(DataError, match=r"traj.txt:2: expected a rigid 4x4 transform"):
        ReplicaSequence(small, intrinsics=K_SMALL)
    traj.unlink()
    assert ReplicaSequence(small, intrinsics=K_SMALL).gt_poses is None


def test_corrupt_images_at_load(small):
    seq = ReplicaSequence(small, intrinsics=K_SMALL)
    (small / "results" / "frame000001.png").write_bytes(b"not an image")
    cv2.imwrite(str(small / "results" / "depth000002.png"), np.zeros((30, 41), np.uint16))
    with pytest.raises(DataError, match=r"frame000001.png: cannot read image"):
        seq[1]
    with pytest.raises(DataError, match=r"depth000002.png: depth image is 41x30, expected 40x30"):
        seq[2]
