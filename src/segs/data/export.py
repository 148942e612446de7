"""Write a sequence to disk in the TUM RGB-D, NICE-SLAM Replica or 7-Scenes layout.

Used to build test fixtures from :class:`segs.data.synthetic.SyntheticSequence` and to hand
synthetic data to external tools. Colour is written as 8-bit (PNG for TUM, JPEG or PNG for
Replica), depth as 16-bit PNG in each dataset's scale (values beyond 65535 units are clipped).
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from segs.data.frame import Sequence
from segs.data.poses import matrix_to_quat
from segs.data.replica import DEPTH_SCALE as REPLICA_SCALE
from segs.data.seven_scenes import DEPTH_SCALE as SEVEN_SCENES_SCALE
from segs.data.tum import DEPTH_SCALE as TUM_SCALE


def _bgr8(rgb: np.ndarray) -> np.ndarray:
    return (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)[:, :, ::-1]


def _depth16(depth: np.ndarray, scale: float) -> np.ndarray:
    return np.clip(np.round(depth * scale), 0, 65535).astype(np.uint16)


def write_tum(seq: Sequence, folder: str | Path, frames=None, time_offset: float = 0.0) -> Path:
    """rgb/, depth/ (if the frames have depth), rgb.txt, depth.txt, groundtruth.txt (if known).

    frames: indices to write (default all); timestamps are seq.timestamps + time_offset.
    """
    folder = Path(folder)
    (folder / "rgb").mkdir(parents=True, exist_ok=True)
    rgb_lines, depth_lines, gt_lines = [], [], []
    for i in range(len(seq)) if frames is None else frames:
        f = seq[i]
        t = f"{f.timestamp + time_offset:.6f}"
        cv2.imwrite(str(folder / "rgb" / f"{i:06d}.png"), _bgr8(f.rgb))
        rgb_lines.append(f"{t} rgb/{i:06d}.png")
        if f.depth is not None:
            (folder / "depth").mkdir(exist_ok=True)
            cv2.imwrite(str(folder / "depth" / f"{i:06d}.png"), _depth16(f.depth, TUM_SCALE))
            depth_lines.append(f"{t} depth/{i:06d}.png")
        if f.pose_c2w is not None:
            q = matrix_to_quat(f.pose_c2w[:3, :3])[0]
            gt_lines.append(" ".join([t] + [f"{v:.9f}" for v in (*f.pose_c2w[:3, 3], *q)]))
    header = "# written by segs.data.export.write_tum\n# timestamp "
    (folder / "rgb.txt").write_text(header + "filename\n" + "\n".join(rgb_lines) + "\n")
    if depth_lines:
        (folder / "depth.txt").write_text(header + "filename\n" + "\n".join(depth_lines) + "\n")
    if gt_lines:
        gt_text = header + "tx ty tz qx qy qz qw\n" + "\n".join(gt_lines) + "\n"
        (folder / "groundtruth.txt").write_text(gt_text)
    return folder


def write_replica(seq: Sequence, folder: str | Path, frames=None, ext: str = "jpg") -> Path:
    """results/frameNNNNNN.<ext>, results/depthNNNNNN.png and traj.txt (poses must be known)."""
    folder = Path(folder)
    (folder / "results").mkdir(parents=True, exist_ok=True)
    traj = []
    for k, i in enumerate(range(len(seq)) if frames is None else frames):
        f = seq[i]
        cv2.imwrite(str(folder / "results" / f"frame{k:06d}.{ext}"), _bgr8(f.rgb))
        if f.depth is not None:
            cv2.imwrite(str(folder / "results" / f"depth{k:06d}.png"), _depth16(f.depth, REPLICA_SCALE))
        traj.append(" ".join(f"{v:.12g}" for v in f.pose_c2w.reshape(-1)))
    (folder / "traj.txt").write_text("\n".join(traj) + "\n")
    return folder


def write_seven_scenes(seq: Sequence, folder: str | Path, frames=None, ext: str = "png") -> Path:
    """frame-NNNNNN.color.<ext>, .depth.png (millimetres) and .pose.txt (4x4 c2w) in `folder`.

    The camera is written to folder/camera-intrinsics.txt; depth is registered to it, so reading
    the folder back needs the same intrinsics for colour and a zero depth_to_color.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for k, i in enumerate(range(len(seq)) if frames is None else frames):
        f = seq[i]
        stem = folder / f"frame-{k:06d}"
        cv2.imwrite(f"{stem}.color.{ext}", _bgr8(f.rgb))
        if f.depth is not None:
            cv2.imwrite(f"{stem}.depth.png", _depth16(f.depth, SEVEN_SCENES_SCALE))
        if f.pose_c2w is not None:
            np.savetxt(f"{stem}.pose.txt", f.pose_c2w, fmt="%.12e")
    np.savetxt(folder / "camera-intrinsics.txt", seq.camera.K, fmt="%.12e")
    return folder
