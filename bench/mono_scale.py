"""Where a monocular map loses its scale, measured against the ground truth on real frames.

    python bench/mono_scale.py                                   # KITTI 51 frames, defaults
    python bench/mono_scale.py --experiment seven_scenes_mono --frames 0 300
    python bench/mono_scale.py --override slam.init.min_parallax_deg=1.0

Runs the monocular frontend single-threaded (deterministic, as `segs.track +experiment=...` with
the same overrides) frame by frame and measures, with the ground-truth poses:
- the initialisation: its two frames, the true baseline and rotation between them, the
  estimated translation direction's error, and the initial map's depths against the depths the
  same keypoint pairs triangulate to under the true poses (ratios normalised by their median:
  1.0 everywhere for an undistorted map), by thirds of the true depth;
- per frame, at the moment it is tracked: the scale of its step (estimated step length in map
  units / true step length) and the frame's inliers; per keyframe, after its local mapping: the
  scale of its map (median over its points of estimated depth / the depth the points'
  observations triangulate to under the true keyframe poses, points whose true rays part by at
  least 1 degree), its new points and their depth against the ground truth;
- at the end: the same map scale of each keyframe after all later bundle adjustments, and the
  step scale of the final trajectory (segs.trajectory.step_scale).
A map without drift has one scale everywhere; a step scale that falls while the keyframes' map
scale stays says tracking shortens the steps; a map scale that falls with it says new points
inherit (or cause) the shrink. JSON: outputs/bench/mono_scale/<time>.json.
"""
from __future__ import annotations

import argparse
import datetime
import json

import _harness

_harness.apply_process_settings()  # before torch loads

import cv2
import numpy as np


def gt_w2c(seq, index: int) -> np.ndarray:
    return np.linalg.inv(seq.gt_poses[index])


def triangulate_gt(seq, fe, pid: int, K: np.ndarray, min_parallax_deg: float = 1.0):
    """Point pid triangulated (linear, all its keyframe observations) under the true poses ->
    (world point [3] or None, parallax in degrees between its widest true rays)."""
    m = fe.map
    rows, centres, rays = [], [], []
    for k, i in m.obs[pid].items():
        kf = m.kfs.get(k)
        if kf is None:
            continue
        T = gt_w2c(seq, kf.frame_index)
        P = K @ T[:3]
        u, v = kf.kp.uv[i]
        rows += [u * P[2] - P[0], v * P[2] - P[1]]
        c = -T[:3, :3].T @ T[:3, 3]
        ray = T[:3, :3].T @ np.linalg.solve(K, [u, v, 1.0])
        centres.append(c)
        rays.append(ray / np.linalg.norm(ray))
    if len(rays) < 2:
        return None, 0.0
    rays = np.array(rays)
    cos = np.clip(rays @ rays.T, -1, 1)
    parallax = float(np.degrees(np.arccos(cos.min())))
    X = np.linalg.svd(np.array(rows))[2][-1]
    if abs(X[3]) < 1e-12 or parallax < min_parallax_deg:
        return None, parallax
    return X[:3] / X[3], parallax


def keyframe_scale(seq, fe, kf, K: np.ndarray) -> dict:
    """Median over kf's points of estimated depth in kf / true depth (points with a true
    triangulation of >= 1 degree parallax), their count and inter-quartile range."""
    m = fe.map
    idx = np.flatnonzero(kf.points >= 0)
    ratios = []
    T = gt_w2c(seq, kf.frame_index)
    for p in kf.points[idx].tolist():
        if not m.valid[p]:
            continue
        Xg, _ = triangulate_gt(seq, fe, p, K)
        if Xg is None:
            continue
        zg = (T[:3, :3] @ Xg + T[:3, 3])[2]
        ze = (kf.w2c[:3, :3] @ m.pos[p] + kf.w2c[:3, 3])[2]
        if zg > 0 and ze > 0:
            ratios.append(ze / zg)
    if not ratios:
        return {"n": 0}
    r = np.array(ratios)
    q1, med, q3 = np.percentile(r, [25, 50, 75])
    return {"n": len(r), "median": float(med), "iqr_rel": float((q3 - q1) / med)}


def init_report(seq, fe, K: np.ndarray) -> dict:
    """The initial two keyframes: frames, true motion, translation-direction error, map depths."""
    m = fe.map
    k0, k1 = sorted(m.kfs)[:2]
    kf0, kf1 = m.kfs[k0], m.kfs[k1]
    T0, T1 = gt_w2c(seq, kf0.frame_index), gt_w2c(seq, kf1.frame_index)
    rel_gt = T1 @ np.linalg.inv(T0)
    rel_est = kf1.w2c @ np.linalg.inv(kf0.w2c)
    t_gt, t_est = rel_gt[:3, 3], rel_est[:3, 3]
    ang = np.degrees(np.arccos(np.clip(t_gt @ t_est / np.linalg.norm(t_gt) / np.linalg.norm(t_est), -1, 1)))
    rot = np.degrees(np.linalg.norm(cv2.Rodrigues(rel_gt[:3, :3])[0]))
    # depths of the initial points in kf0: estimated vs true-pose triangulation of the same pair
    _, pids = m.kf_point_ids(kf0)
    ze, zg, par = [], [], []
    for p in pids.tolist():
        if k1 not in m.obs[p]:
            continue
        Xg, parallax = triangulate_gt(seq, fe, p, K, min_parallax_deg=0.0)
        if Xg is None:
            continue
        zg.append((T0[:3, :3] @ Xg + T0[:3, 3])[2])
        ze.append((kf0.w2c[:3, :3] @ m.pos[p] + kf0.w2c[:3, 3])[2])
        par.append(parallax)
    ze, zg, par = np.array(ze), np.array(zg), np.array(par)
    ok = (zg > 0) & (ze > 0)
    ratio = ze[ok] / zg[ok]
    ratio_rel = ratio / np.median(ratio)
    thirds = np.array_split(np.argsort(zg[ok]), 3)
    return {
        "frames": [kf0.frame_index, kf1.frame_index], "points": int(len(pids)),
        "true_baseline_m": float(np.linalg.norm(t_gt)), "true_rotation_deg": float(rot),
        "translation_direction_error_deg": float(ang),
        "parallax_deg_percentiles_10_50_90": np.percentile(par, [10, 50, 90]).tolist() if len(par) else [],
        "true_depth_m_percentiles_10_50_90": np.percentile(zg[ok], [10, 50, 90]).tolist() if ok.any() else [],
        # est / true depth relative to the median, by thirds of the true depth (near, mid, far)
        "depth_ratio_by_true_depth_third": [float(np.median(ratio_rel[t])) for t in thirds],
        "depth_ratio_iqr_rel": float(np.subtract(*np.percentile(ratio_rel, [75, 25]))),
    }


def run(experiment: str, root: str | None, frames, overrides: list[str]) -> dict:
    from segs.config import compose, instantiate, make_sequence
    from segs.trajectory import ate, step_scale

    args = [f"+experiment={experiment}", *([f"data.root={root}"] if root else []),
            *([f"data.frames=[{frames[0]},{frames[1]}]"] if frames else []), *overrides]  # fmt: skip
    cfg = compose(args, output_dir="/tmp/segs_bench_mono_scale")
    seq = make_sequence(cfg.data)
    fe = instantiate(cfg.slam)(camera=seq.camera, sensor=seq.sensor)
    K = seq.camera.K
    per_frame, per_kf, init = [], {}, None
    prev = None  # (index, estimated centre, true centre) of the last tracked frame
    for i in range(len(seq)):
        res = fe.process(seq[i])
        if init is None and len(fe.map.kfs) >= 2:
            init = init_report(seq, fe, K)
            print(f"init: {json.dumps(init)}", flush=True)
        if res.w2c is None:
            continue
        c_est = -res.w2c[:3, :3].T @ res.w2c[:3, 3]
        c_gt = seq.gt_poses[i][:3, 3]
        if prev is not None and prev[0] == i - 1:
            s = np.linalg.norm(c_est - prev[1]) / max(np.linalg.norm(c_gt - prev[2]), 1e-9)
            inl = int(((fe.tracker.last.points >= 0)).sum()) if fe.tracker.last is not None else None
            per_frame.append({"frame": i, "step_scale": float(s), "tracked_points": inl})
        prev = (i, c_est, c_gt)
        if res.kf_id is not None and res.kf_id in fe.map.kfs:
            kf = fe.map.kfs[res.kf_id]
            sc = keyframe_scale(seq, fe, kf, K)
            per_kf[res.kf_id] = {"frame": i, "at_creation": sc}
            step = per_frame[-1]["step_scale"] if per_frame else float("nan")
            print(f"frame {i}: keyframe {res.kf_id}, step scale {step:.4f}, map scale "
                  f"{sc.get('median', float('nan')):.4f} (iqr {sc.get('iqr_rel', float('nan')):.2f}, "
                  f"{sc['n']} points), {len(fe.map.kfs)} keyframes", flush=True)  # fmt: skip
    fe.finish()
    for k, d in per_kf.items():
        kf = fe.map.kfs.get(k)
        d["at_end"] = keyframe_scale(seq, fe, kf, K) if kf is not None else None
    traj = fe.trajectory()
    return {"args": args, "init": init, "frames": per_frame, "keyframes": per_kf,
            "ate_sim3_m": ate(seq.timestamps, traj, seq.gt_poses, "sim3")["rmse"],
            "step_scale": step_scale(seq.timestamps, traj, seq.gt_poses)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--experiment", default="kitti_mono")
    ap.add_argument("--root", default=None, help="data.root (default: the experiment's)")
    ap.add_argument("--frames", type=int, nargs=2, default=None, help="data.frames [start, stop)")
    ap.add_argument("--override", nargs="*", default=[], help="config overrides, as on the segs.track command line")
    a = ap.parse_args()
    out = run(a.experiment, a.root, a.frames, a.override)
    ends = [(k, d["at_end"]["median"]) for k, d in out["keyframes"].items() if d.get("at_end") and d["at_end"]["n"]]
    print("map scale of each keyframe at the end: " + ", ".join(f"{k}:{v:.3f}" for k, v in ends))
    s, a_ = out["step_scale"], out["ate_sim3_m"]
    print(f"ATE (Sim(3)) {'n/a' if a_ is None else f'{a_:.4f} m'}; step scale (5 steps) min / max x median "
          f"{s.get('min_rel') or float('nan'):.2f} / {s.get('max_rel') or float('nan'):.2f}")  # fmt: skip
    path = _harness.OUTPUTS / "mono_scale" / f"{datetime.datetime.now():%Y%m%d-%H%M%S}.json"
    print(f"-> {_harness.write_json(path, {**out, **_harness.record()})}")


if __name__ == "__main__":
    main()
