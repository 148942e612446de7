"""Trajectory files and the absolute trajectory error (ATE), computed with evo.

Estimated poses come as world-to-camera matrices keyed by frame index (what the frontends
produce); ground truth comes as camera-to-world matrices per frame (what the readers produce).

evo's file module is imported by the two functions that read and write TUM files: it loads
rosbags, ruamel.yaml and apsw (about 5 MB resident), which a training run needs only once it
writes its trajectory (docs/decisions/029-peak-memory.md).
"""
from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
from evo.core import metrics, sync
from evo.core.geometry import GeometryException, umeyama_alignment
from evo.core.trajectory import PoseTrajectory3D

ALIGNMENTS = ("se3", "sim3", "none")
# ATE "reason" of a run whose poses are the ground truth itself
GROUND_TRUTH_POSES = "ground-truth poses"


def _trajectory(timestamps: np.ndarray, c2w: np.ndarray) -> PoseTrajectory3D:
    """timestamps [M] seconds, c2w [M,4,4] -> evo trajectory."""
    return PoseTrajectory3D(poses_se3=[np.asarray(p, np.float64) for p in c2w], timestamps=np.asarray(timestamps, np.float64))


def estimated_c2w(trajectory: dict[int, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Frame-index-keyed w2c dict -> (frame indices [M] sorted, c2w [M,4,4])."""
    idx = np.array(sorted(trajectory), dtype=np.int64)
    c2w = np.stack([np.linalg.inv(trajectory[i]) for i in idx]) if len(idx) else np.zeros((0, 4, 4))
    return idx, c2w


def write_trajectory(path: str | Path, timestamps: np.ndarray, trajectory: dict[int, np.ndarray]) -> int:
    """Frame-index-keyed w2c dict -> TUM file of those frames at timestamps[index] (an empty file
    when the dict is empty: evo writes none); returns the number of poses written."""
    idx, c2w = estimated_c2w(trajectory)
    if len(idx):
        write_tum(path, np.asarray(timestamps)[idx], c2w)
    else:
        Path(path).write_text("")
    return len(idx)


def write_tum(path: str | Path, timestamps: np.ndarray, c2w: np.ndarray) -> None:
    """Write camera-to-world poses [M,4,4] at timestamps [M] in TUM format (tx ty tz qx qy qz qw)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    from evo.tools import file_interface

    file_interface.write_tum_trajectory_file(str(tmp), _trajectory(timestamps, c2w))
    tmp.replace(path)


def lost_ranges(lost: list[int]) -> list[list[int]]:
    """Frame indices -> inclusive runs, sorted: [3, 4, 5, 9] -> [[3, 5], [9, 9]]."""
    runs: list[list[int]] = []
    for i in sorted(lost):
        if runs and i == runs[-1][1] + 1:
            runs[-1][1] = i
        else:
            runs.append([i, i])
    return runs


def frontend_ate(frontend, timestamps: np.ndarray, trajectory: dict[int, np.ndarray], gt_c2w: np.ndarray | None,
                 align: str) -> dict:  # fmt: skip
    """ATE of a frontend's trajectory (see ate); n/a with the reason GROUND_TRUTH_POSES for a
    frontend that replays the dataset's poses (slam=known_poses): there is no estimate to score."""
    if getattr(frontend, "uses_ground_truth_poses", False):
        return ate_not_measured(align, GROUND_TRUTH_POSES)
    return ate(timestamps, trajectory, gt_c2w, align=align)


def ate_not_measured(align: str, reason: str) -> dict:
    """The ATE record of a run whose trajectory is not an estimate to score (e.g. the frontend
    replays ground-truth poses): every figure None, `reason` saying why."""
    return {"rmse": None, "mean": None, "median": None, "max": None, "pairs": 0, "align": align, "scale": None,
            "reason": reason}  # fmt: skip


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """A TUM trajectory file -> (timestamps [M], c2w [M,4,4]); an empty file gives M = 0."""
    if Path(path).stat().st_size == 0:
        return np.zeros(0), np.zeros((0, 4, 4))
    from evo.tools import file_interface

    traj = file_interface.read_tum_trajectory_file(str(path))
    return np.asarray(traj.timestamps, np.float64), np.stack(traj.poses_se3).astype(np.float64)


def alignment(est_t: np.ndarray, est_c2w: np.ndarray, gt_t: np.ndarray, gt_c2w: np.ndarray, align: str = "se3",
              max_diff: float = 0.1) -> tuple[np.ndarray, np.ndarray, float] | None:  # fmt: skip
    """(R [3,3], t [3], s) with ground-truth centres ~ s R est + t (Umeyama on the poses associated
    by timestamp, as `ate` aligns; s = 1 unless align is "sim3"; identity for "none"), or None
    with fewer than 3 associated poses or degenerate centres. est_t [M], est_c2w [M,4,4]; gt_t [N],
    gt_c2w [N,4,4] (NaN rows where unknown)."""
    if align not in ALIGNMENTS:
        raise ValueError(f"align must be one of {ALIGNMENTS}, got {align!r}")
    ok = np.isfinite(gt_c2w.reshape(len(gt_c2w), -1)).all(axis=1)
    if len(est_t) < 3 or ok.sum() < 3:
        return None
    ref, traj = sync.associate_trajectories(_trajectory(gt_t[ok], gt_c2w[ok]), _trajectory(est_t, est_c2w), max_diff=max_diff)
    if ref.num_poses < 3:
        return None
    if align == "none":
        return np.eye(3), np.zeros(3), 1.0
    try:
        r, t, s = umeyama_alignment(traj.positions_xyz.T, ref.positions_xyz.T, align == "sim3")
    except GeometryException:
        return None
    return r, t, float(s)


def ate(
    timestamps: np.ndarray,
    trajectory: dict[int, np.ndarray],
    gt_c2w: np.ndarray | None,
    align: str = "se3",
    max_diff: float = 0.1,
) -> dict:
    """ATE RMSE (metres) of estimated poses against ground truth, aligned with evo.

    timestamps: [N] seconds of every frame of the sequence; trajectory: frame index -> w2c [4,4]
    of the tracked frames; gt_c2w: [N,4,4] ground truth (NaN rows where unknown) or None.
    align: "se3" (RGB-D, stereo), "sim3" (monocular: scale corrected) or "none". When the
    camera centres are degenerate for Umeyama (all on one point, e.g. a pan in place) the first
    poses are aligned instead and "align" says "origin".
    Returns {"rmse", "mean", "median", "max", "pairs", "align", "scale"}, or {"rmse": None, ...}
    with a "reason" when it cannot be computed (no ground truth, fewer than 3 pairs).
    """
    if align not in ALIGNMENTS:
        raise ValueError(f"align must be one of {ALIGNMENTS}, got {align!r}")
    empty = ate_not_measured(align, "")
    if gt_c2w is None:
        return {**empty, "reason": "no ground truth"}
    idx, est = estimated_c2w(trajectory)
    ok = np.isfinite(gt_c2w.reshape(len(gt_c2w), -1)).all(axis=1)
    gt_idx = np.nonzero(ok)[0]
    if len(idx) < 3 or len(gt_idx) < 3:
        return {**empty, "reason": "fewer than 3 tracked frames with ground truth"}
    ref = _trajectory(timestamps[gt_idx], gt_c2w[gt_idx])
    traj = _trajectory(timestamps[idx], est)
    ref, traj = sync.associate_trajectories(ref, traj, max_diff=max_diff)
    if ref.num_poses < 3:
        return {**empty, "reason": "fewer than 3 associated poses"}
    traj = copy.deepcopy(traj)
    scale, used = 1.0, align
    if align != "none":
        try:
            _, _, scale = traj.align(ref, correct_scale=(align == "sim3"))
        except GeometryException:  # camera centres on a point or a line (rotation in place)
            traj.align_origin(ref)
            used = "origin"
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, traj))
    s = ape.get_all_statistics()
    return {
        "rmse": float(s["rmse"]),
        "mean": float(s["mean"]),
        "median": float(s["median"]),
        "max": float(s["max"]),
        "pairs": int(ref.num_poses),
        "align": used,
        "scale": float(scale),
    }


def step_scale(
    timestamps: np.ndarray,
    trajectory: dict[int, np.ndarray],
    gt_c2w: np.ndarray,
    window: int = 5,
    max_diff: float = 0.1,
) -> dict:
    """How the scale of an estimated trajectory holds along a sequence (monocular drift).

    After the Sim(3) alignment of the whole trajectory to the ground truth (evo, as `ate`), the
    ratio of estimated to true path length over every `window` consecutive steps of the tracked
    frames (sliding by one step): 1 everywhere for a trajectory without scale drift.
    timestamps [N], trajectory (frame index -> w2c [4,4]) and gt_c2w [N,4,4] as in `ate`.
    Returns {"ratios": [W] list, "median", "min_rel", "max_rel" (min / max over median), "window"},
    or {"ratios": [], ..., "reason"} when fewer than `window` steps have ground truth.
    """
    empty = {"ratios": [], "median": None, "min_rel": None, "max_rel": None, "window": window}
    idx, est = estimated_c2w(trajectory)
    ok = np.isfinite(gt_c2w.reshape(len(gt_c2w), -1)).all(axis=1)
    gt_idx = np.nonzero(ok)[0]
    if len(idx) < window + 1 or len(gt_idx) < window + 1:
        return {**empty, "reason": f"fewer than {window} steps with ground truth"}
    ref = _trajectory(timestamps[gt_idx], gt_c2w[gt_idx])
    traj = _trajectory(timestamps[idx], est)
    ref, traj = sync.associate_trajectories(ref, traj, max_diff=max_diff)
    if ref.num_poses < window + 1:
        return {**empty, "reason": f"fewer than {window} associated steps"}
    traj = copy.deepcopy(traj)
    try:
        traj.align(ref, correct_scale=True)
    except GeometryException:  # camera centres on a point or a line: no scale to compare
        return {**empty, "reason": "degenerate alignment"}
    d_est = np.linalg.norm(np.diff(traj.positions_xyz, axis=0), axis=1)
    d_ref = np.linalg.norm(np.diff(ref.positions_xyz, axis=0), axis=1)
    kernel = np.ones(window)
    true_len = np.convolve(d_ref, kernel, "valid")
    ratios = np.convolve(d_est, kernel, "valid") / np.where(true_len > 0, true_len, np.nan)
    ratios = ratios[np.isfinite(ratios)]
    if not len(ratios):
        return {**empty, "reason": "the ground truth does not move"}
    med = float(np.median(ratios))
    return {"ratios": ratios.tolist(), "median": med, "min_rel": float(ratios.min() / med),
            "max_rel": float(ratios.max() / med), "window": window}
