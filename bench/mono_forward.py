"""Monocular scale on forward motion and on real 30 Hz frames: segs' frontend vs two-view odometry.

    python bench/mono_forward.py                       # forward corridor at 2 speeds + 7-Scenes
    python bench/mono_forward.py --runs 3 --frames 60 --skip-7scenes
    python bench/mono_forward.py --scenes-frames 200   # a shorter 7-Scenes slice

Sequences (monocular, 640x480):
- the synthetic corridor (`SyntheticSequence(trajectory="forward")`, exact poses) at two speeds,
  by default 1.2 and 2.4 stretches of 24 m over --frames frames: about 10 % and 20 % of the median
  scene depth (4.8 m) per frame;
- the shared 7-Scenes redkitchen frames (600 real 30 Hz Kinect frames; skipped with a note when
  the folder is absent), `SevenScenesSequence` (colour camera calibration, ground truth in the
  colour camera), the first --scenes-frames frames.

Methods, on the same frames:
- segs: `slam_frontend(camera, "mono")` with the conf/slam/orb.yaml defaults, single-threaded
  (deterministic); every frame fed in order;
- two-view: the naive essential-matrix odometry of issue 10 (no map, no BA): ORB features of
  consecutive frames (segs' extractor, same settings), ratio-test matches, `cv2.findEssentialMat`
  (RANSAC) + `cv2.recoverPose`, each step a unit translation; the chained poses are then
  Sim(3)-aligned like segs' (the alignment picks one global scale). A step without a pose
  (fewer than 8 matches or RANSAC failure) repeats the previous step.

Printed and written (JSON, default outputs/bench/mono_forward.json) per sequence and method:
Sim(3) ATE RMSE (evo, segs.trajectory.ate), ATE as % of the ground-truth path length, the
alignment scale, tracked frames (and frames lost before initialisation), keyframes, frames/s
(end to end, process() time) and ms/frame of tracking (median over frames). Accuracy is
deterministic; the timings are medians over --runs runs (the machine load is recorded).
"""
from __future__ import annotations

import argparse
import os
import time

import _harness

_harness.apply_process_settings()  # before torch loads

import cv2
import numpy as np

from segs.config import slam_frontend
from segs.data.seven_scenes import SevenScenesSequence
from segs.data.synthetic import SyntheticSequence
from segs.slam.config import group_from_yaml
from segs.slam.estimation.matching import match_descriptors
from segs.slam.features.extractor import OrbExtractor, to_gray
from segs.trajectory import ate

SCENES = _harness.SEVEN_SCENES


def path_length(gt_c2w: np.ndarray) -> float:
    """Length (m) of the ground-truth camera path [N,4,4] (sum of the steps)."""
    return float(np.linalg.norm(np.diff(gt_c2w[:, :3, 3], axis=0), axis=1).sum())


def two_view_odometry(frames, K: np.ndarray, extractor: OrbExtractor, ratio: float = 0.8,
                      ransac_px: float = 1.0, seed: int = 0) -> tuple[dict[int, np.ndarray], int, float]:
    """Essential-matrix odometry between consecutive frames with unit-length steps.

    frames: segs Frames in order; K [3,3]. Returns (frame index -> w2c [4,4] for every frame,
    the first one the identity; the number of steps that had no pose of their own and repeated
    the previous step; seconds spent computing, frame loading excluded).
    """
    cv2.setRNGSeed(seed)
    w2c = np.eye(4)
    step = np.eye(4)
    out, failed, prev, busy = {}, 0, None, 0.0
    for f in frames:
        t0 = time.perf_counter()
        kp = extractor.extract(to_gray(f.rgb))
        if prev is not None:
            rel = _relative_pose(prev, kp, K, ratio, ransac_px)
            if rel is None:
                failed += 1
            else:
                step = rel
            w2c = step @ w2c
        out[f.index] = w2c.copy()
        prev = kp
        busy += time.perf_counter() - t0
    return out, failed, busy


def _relative_pose(kp1, kp2, K, ratio, ransac_px) -> np.ndarray | None:
    """w2c of view 2 in view 1's frame [4,4] with a unit translation, or None."""
    i1, i2 = match_descriptors(kp1.desc, kp2.desc, ratio=ratio, max_dist=64)
    if len(i1) < 8:
        return None
    x1, x2 = kp1.uv[i1], kp2.uv[i2]
    E, mask = cv2.findEssentialMat(x1, x2, K, cv2.RANSAC, 0.999, ransac_px)
    if E is None or E.shape != (3, 3):
        E = None if E is None or E.shape[0] < 3 else E[:3]
    if E is None:
        return None
    n, R, t, _ = cv2.recoverPose(E, x1, x2, K, mask=mask)
    if n < 5:
        return None
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t.ravel() / max(np.linalg.norm(t), 1e-12)
    return T


def _summary(seq, traj, length, extra) -> dict:
    res = ate(seq.timestamps, traj, seq.gt_poses, "sim3")
    rmse = res["rmse"]
    return {"ate_m": rmse, "ate_pct_path": None if rmse is None else 100 * rmse / length,
            "align_scale": res["scale"], "tracked": len(traj), "frames": len(seq), **extra}


def run_segs(seq, frames) -> tuple[dict, dict]:
    """One single-threaded frontend run -> (accuracy summary, timings)."""
    fe = slam_frontend(seq.camera, "mono")
    process_s = 0.0
    for f in frames:
        t0 = time.perf_counter()
        fe.process(f)
        process_s += time.perf_counter() - t0
    fe.finish()
    traj = fe.trajectory()
    lost = fe.lost_frames()
    first = min(traj) if traj else None
    extra = {"lost": len(lost), "lost_before_init": sum(1 for i in lost if first is None or i < first),
             "keyframes": len(fe.keyframe_frames()), "culled_keyframes": len(fe.map.culled)}
    timing = {"fps": len(frames) / process_s, "tracking_ms": float(np.median(fe.times["track"]) * 1e3),
              "mapping_ms_per_kf": float(np.median(fe.times["mapping"]) * 1e3) if fe.times["mapping"] else None}
    return _summary(seq, traj, path_length(seq.gt_poses), extra), timing


def run_two_view(seq, frames) -> tuple[dict, dict]:
    fc = group_from_yaml("features")
    ex = OrbExtractor.from_config(fc)
    traj, failed, s = two_view_odometry(frames, seq.camera.K, ex)
    return _summary(seq, traj, path_length(seq.gt_poses), {"failed_steps": failed}), {"fps": len(frames) / s}


def bench(name: str, seq, runs: int) -> dict:
    # short sequences are decoded / rendered once; long ones stream (loading is never timed)
    frames = [seq[i] for i in range(len(seq))] if len(seq) <= 120 else _Frames(seq)
    out = {"frames": len(seq), "path_m": path_length(seq.gt_poses)}
    for method, fn in (("segs", run_segs), ("two_view", run_two_view)):
        rows = [fn(seq, frames) for _ in range(runs)]
        acc = rows[0][0]
        timing = {k: v for k, v in _harness.medians([r[1] for r in rows]).items() if v is not None}
        out[method] = {**acc, **timing}
        a = out[method]
        print(f"{name} [{method}]: ATE {_fmt(a['ate_m'], 100, 'cm')} ({_fmt(a['ate_pct_path'], 1, '%')} of "
              f"{out['path_m']:.1f} m), scale {_fmt(a['align_scale'], 1, '')}, tracked {a['tracked']}/{a['frames']}"
              + (f" (lost {a['lost']}, {a['lost_before_init']} before init), {a['keyframes']} kfs"
                 if method == "segs" else f" ({a['failed_steps']} steps without a pose)")
              + f", {a['fps']:.1f} frames/s" + (f", tracking {a['tracking_ms']:.1f} ms" if "tracking_ms" in a else ""),
              flush=True)
    s, b = out["segs"]["ate_m"], out["two_view"]["ate_m"]
    out["segs_better"] = s is not None and (b is None or s < b)
    return out


def _fmt(v, mult, unit) -> str:
    return "n/a" if v is None else f"{v * mult:.2f} {unit}".rstrip()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3, help="repeated runs (timings: median)")
    ap.add_argument("--frames", type=int, default=60, help="frames of each forward sequence")
    ap.add_argument("--speeds", type=float, nargs="+", default=[1.2, 2.4])
    ap.add_argument("--size", type=int, nargs=2, default=[640, 480])
    ap.add_argument("--scenes-frames", type=int, default=600)
    ap.add_argument("--skip-7scenes", action="store_true")
    ap.add_argument("--out", default=str(_harness.OUTPUTS / "mono_forward.json"))
    a = ap.parse_args()
    results = {**_harness.record(), "runs": a.runs, "sequences": {}}
    w, h = a.size
    for speed in a.speeds:
        seq = SyntheticSequence(sensor="mono", n_frames=a.frames, width=w, height=h, trajectory="forward",
                                speed=speed, seed=0)
        step = path_length(seq.gt_poses) / (len(seq) - 1)
        name = f"forward_speed{speed:g}_{w}x{h}"
        print(f"{name}: {len(seq)} frames, {step:.2f} m per frame", flush=True)
        results["sequences"][name] = {"speed": speed, "step_m": step, **bench(name, seq, a.runs)}
    if a.skip_7scenes:
        pass
    elif not SCENES.is_dir():
        print(f"7-Scenes: skipped, {SCENES} is absent")
    else:
        seq = SevenScenesSequence(root=SCENES, sensor="mono", frames=[0, a.scenes_frames])
        name = f"7scenes_redkitchen_{len(seq)}"
        results["sequences"][name] = bench(name, seq, a.runs)
    results["machine"]["load_avg_end"] = _harness.load_average()
    _harness.write_json(a.out, results)
    print(f"-> {a.out} (load average {results['machine']['load_avg'][0]:.1f} -> "
          f"{results['machine']['load_avg_end'][0]:.1f} on {os.cpu_count()} cores)")


class _Frames:
    """Iterable over a sequence's frames, loaded on demand (each pass reloads)."""

    def __init__(self, seq):
        self.seq = seq

    def __len__(self) -> int:
        return len(self.seq)

    def __iter__(self):
        return (self.seq[i] for i in range(len(self.seq)))


if __name__ == "__main__":
    main()
