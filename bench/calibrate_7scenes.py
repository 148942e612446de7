"""Measure the 7-Scenes colour camera: focal length and depth -> colour registration.

7-Scenes publishes one set of intrinsics (585, 585, 320, 240): the depth camera's; its poses
are the depth camera's (KinectFusion). The colour camera of a Kinect v1 is another lens, a few
centimetres to the side. Two measurements on the real frames, no calibration target needed:

1. focal length: ORB matches between frames i and i+10 must satisfy the epipolar constraint of
   the ground-truth relative pose; the median Sampson error over all pairs is minimal at the
   true focal length (a 3-4 cm baseline between the cameras barely moves it);
2. registration: depth edges, warped into the colour image (cv2.registerDepth) with a candidate
   translation and principal point, must lie on the colour image's edges; the mean colour
   gradient under the depth edges is maximal at the right values (coarse grid, then a local
   search).

3. with --lens, instead: the radial distortion k1 of the two lenses. (a) The edge score of 2. at the
   reader's registration with the colour image and the raw depth each undistorted with a k1 (nearest
   pixel for depth): equal k1 for both lenses against the colour lens alone. (b) The median Sampson
   distance of RANSAC-consistent SIFT matches (bench/ate_diagnostics.py), undistorted with (f, k1),
   under the ground truth's relative poses, per half of the frames (0-299, 300-599): pairs 10 and 30
   frames apart, every 10 frames.

4. with --self-calibration, instead: the focal length from the images alone, no ground truth
   (Mendonca and Cipolla's criterion): for frame pairs 20 and 40 frames apart, the fundamental
   matrix of their ORB matches (RANSAC at 1 px, then least squares on its inliers) makes an
   essential matrix K^T F K whose two non-zero singular values are equal at the true K; the mean
   of (s1 - s2) / (s1 + s2) over the pairs per candidate focal length (principal point 323, 240).

    python bench/calibrate_7scenes.py [--root ../shared/data/7scenes_redkitchen_0000_0599]
    python bench/calibrate_7scenes.py --self-calibration
    python bench/calibrate_7scenes.py --lens

Prints both searches and writes outputs/bench/calibrate_7scenes.json. The reader's defaults
(segs.data.seven_scenes.COLOR_INTRINSICS, DEPTH_TO_COLOR, COLOR_DISTORTION, DEPTH_DISTORTION) are the
values this measured. Every measurement reads the frames as recorded (both lenses' distortion zero).
"""
from __future__ import annotations

import argparse
import itertools
from pathlib import Path

import _harness

_harness.apply_process_settings()  # before torch loads

import cv2
import numpy as np

from segs.data.base import lens_maps, undistort
from segs.data.seven_scenes import COLOR_INTRINSICS, DEPTH_TO_COLOR, SevenScenesSequence
from segs.slam.geometry import fundamental, sampson_distance

ROOT = _harness.ROOT
DEPTH_K = np.array([[585.0, 0, 320], [0, 585.0, 240], [0, 0, 1]])  # the published (depth) intrinsics
RAW = {"distortion": [0] * 4, "depth_distortion": [0] * 4}  # the images as recorded


def gray(rgb: np.ndarray) -> np.ndarray:
    """[H,W,3] float in [0,1] -> [H,W] uint8."""
    return cv2.cvtColor((rgb * 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)


def epipolar_pairs(seq, step: int = 40, gap: int = 10) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """ORB matches (x_i [N,2], x_j [N,2]) and the ground-truth relative pose T_ji [4,4] of frame pairs."""
    orb, bf = cv2.ORB_create(2000), cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
    pairs = []
    for i in range(0, len(seq) - gap, step):
        (fi, fj) = seq[i], seq[i + gap]
        ki, di = orb.detectAndCompute(gray(fi.rgb), None)
        kj, dj = orb.detectAndCompute(gray(fj.rgb), None)
        m = bf.match(di, dj)
        xi = np.array([ki[x.queryIdx].pt for x in m])
        xj = np.array([kj[x.trainIdx].pt for x in m])
        pairs.append((xi, xj, np.linalg.inv(fj.pose_c2w) @ fi.pose_c2w))
    return pairs


def sampson(f: float, cx: float, cy: float, xi: np.ndarray, xj: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Sampson distance [N] (px) of matches xi -> xj under relative pose T and pinhole (f, f, cx, cy)."""
    K = np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]])
    return sampson_distance(fundamental(np.eye(4), T, K), xi, xj)


def focal_search(pairs, focals) -> dict[float, float]:
    """Median Sampson error (px, matches under 5 px) per candidate focal length."""
    out = {}
    for f in focals:
        e = np.concatenate([sampson(f, 320, 240, *p) for p in pairs])
        out[float(f)] = float(np.median(e[e < 5]))
    return out


def self_calibration(pairs, focals, cx: float = 323.0, cy: float = 240.0) -> dict[float, float]:
    """Mean singular-value gap (s1 - s2) / (s1 + s2) of K^T F K over the pairs' fundamental
    matrices F (from their matches alone) per candidate focal length (0 for a consistent K)."""
    Fs = []
    for xi, xj, _ in pairs:
        F, mask = cv2.findFundamentalMat(xi, xj, cv2.FM_RANSAC, 1.0, 0.999)
        if F is None or F.shape != (3, 3) or mask.sum() < 30:
            continue
        keep = mask.ravel().astype(bool)
        F, _ = cv2.findFundamentalMat(xi[keep], xj[keep], cv2.FM_8POINT)
        if F is not None and F.shape == (3, 3):
            Fs.append(F)
    out = {}
    for f in focals:
        K = np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]])
        s = np.array([np.linalg.svd(K.T @ F @ K, compute_uv=False) for F in Fs])
        out[float(f)] = float(np.mean((s[:, 0] - s[:, 1]) / (s[:, 0] + s[:, 1])))
    return out


def raw_frames(root: Path, step: int = 15) -> list[tuple[np.ndarray, np.ndarray]]:
    """(raw depth [H,W] m in the depth camera, colour [H,W,3] as recorded) of every step-th frame."""
    seq = SevenScenesSequence(root, sensor="rgbd", intrinsics=[585, 585, 320, 240], depth_to_color=[0] * 6, **RAW)
    return [(seq[i].depth.astype(np.float32), seq[i].rgb) for i in range(0, len(seq), step)]


def edge_frames(raw, k_color: float = 0.0, k_depth: float = 0.0) -> list[tuple[np.ndarray, np.ndarray]]:
    """(depth [H,W] m in the depth camera, colour gradient magnitude [H,W] normalised to mean 1) of
    raw_frames, each image undistorted with its lens's k1 (the colour to COLOR_INTRINSICS's pinhole)."""
    size = raw[0][0].shape[::-1]
    Kc = np.array([[COLOR_INTRINSICS[0], 0, COLOR_INTRINSICS[2]], [0, COLOR_INTRINSICS[1], COLOR_INTRINSICS[3]], [0, 0, 1]])
    color_maps = lens_maps(Kc, np.array([k_color, 0, 0, 0.0]), size)
    depth_maps = lens_maps(DEPTH_K, np.array([k_depth, 0, 0, 0.0]), size)
    out = []
    for depth, rgb in raw:
        g = cv2.GaussianBlur(gray(undistort(rgb, color_maps, cv2.INTER_LINEAR)).astype(np.float32), (5, 5), 1.5)
        grad = np.hypot(cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1))
        out.append((undistort(depth, depth_maps, cv2.INTER_NEAREST), grad / (grad.mean() + 1e-6)))
    return out


def edge_score(frames, f: float, cx: float, cy: float, tx: float, ty: float) -> float:
    """Mean colour gradient under the registered depth's log-depth edges (higher = better aligned)."""
    Kc, T = np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]]), np.eye(4)
    T[:3, 3] = [tx, ty, 0.0]
    score = 0.0
    for depth, grad in frames:
        D = np.nan_to_num(cv2.registerDepth(DEPTH_K, Kc, None, T, depth, (depth.shape[1], depth.shape[0])))
        D = cv2.morphologyEx(D, cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8))  # 1-px holes of the forward warp
        L = np.log(np.maximum(D, 0.1))
        de = np.hypot(cv2.Sobel(L, cv2.CV_32F, 1, 0), cv2.Sobel(L, cv2.CV_32F, 0, 1))
        inside = cv2.erode((D > 0).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0  # no edges at holes
        de = np.where(inside, np.minimum(de, 0.3), 0)[10:-10, 10:-10]
        score += float((de * grad[10:-10, 10:-10]).sum() / (de.sum() + 1e-6))
    return score / len(frames)


def registration_search(frames, f: float) -> dict:
    """Grid over (tx, ty) in metres at the nominal principal point, then a local search over (tx, ty, cx, cy)."""
    base = edge_score(frames, f, 320, 240, 0, 0)
    grid = {(tx, ty): edge_score(frames, f, 320, 240, tx, ty) for tx in np.arange(-0.04, 0.041, 0.01) for ty in np.arange(-0.02, 0.021, 0.01)}
    (tx, ty), best = max(grid.items(), key=lambda kv: kv[1])
    cx, cy = 320.0, 240.0
    for step in (0.005, 0.0025):  # metres; the principal point moves 2 px per 5 mm step
        for _ in range(3):
            cands = [(tx + a * step, ty + b * step, cx + c * 2 * step / 0.005, cy + d * 2 * step / 0.005)
                     for a, b, c, d in itertools.product((-1, 0, 1), repeat=4)]  # fmt: skip
            scores = [edge_score(frames, f, c3, c4, c1, c2) for c1, c2, c3, c4 in cands]
            (tx, ty, cx, cy), best = cands[int(np.argmax(scores))], max(scores)
    return {"unregistered_score": base, "score": best, "tx_m": round(tx, 4), "ty_m": round(ty, 4), "cx": cx, "cy": cy}


def lens_edges(root: Path, ks: list[float]) -> dict:
    """Edge score at the reader's registration per k1: both lenses undistorted alike, the colour alone."""
    f, cx, cy = COLOR_INTRINSICS[0], COLOR_INTRINSICS[2], COLOR_INTRINSICS[3]
    tx, ty, raw = DEPTH_TO_COLOR[3], DEPTH_TO_COLOR[4], raw_frames(root)
    both = {k: edge_score(edge_frames(raw, k_color=k, k_depth=k), f, cx, cy, tx, ty) for k in ks}
    colour = {k: edge_score(edge_frames(raw, k_color=k), f, cx, cy, tx, ty) for k in ks if k}
    return {"both_lenses": both, "colour_lens_only": colour}


def lens_sampson(root: Path, focals: list[float], ks: list[float]) -> dict:
    """Median over frame pairs of the median Sampson distance (px) of their consistent SIFT matches,
    undistorted with (f, k1), under the ground truth's relative pose: {half: {f: {k1: px}}}."""
    from ate_diagnostics import consistent_matches
    from segs.slam.geometry import inv_se3

    seq = SevenScenesSequence(root, sensor="mono", **RAW)
    sift, pairs = cv2.SIFT_create(), []
    for gap in (10, 30):
        for i in range(0, len(seq) - gap, 10):
            m = consistent_matches(gray(seq[i].rgb), gray(seq[i + gap].rgb), sift)
            if m is not None:
                pairs.append((i, i + gap, m[0], m[1]))
    out = {}
    for f in focals:
        K = np.array([[f, 0, COLOR_INTRINSICS[2]], [0, f, COLOR_INTRINSICS[3]], [0, 0, 1.0]])
        for k in ks:
            halves: dict[str, list[float]] = {"0-299": [], "300-599": []}
            for i, j, xi, xj in pairs:
                u = [cv2.undistortPoints(x.reshape(-1, 1, 2), K, np.array([k, 0, 0, 0.0]), P=K).reshape(-1, 2) for x in (xi, xj)]
                F = fundamental(inv_se3(seq.gt_poses[i]), inv_se3(seq.gt_poses[j]), K)
                halves["0-299" if j < 300 else "300-599"].append(float(np.median(sampson_distance(F, *u))))
            for h, v in halves.items():
                out.setdefault(h, {}).setdefault(float(f), {})[float(k)] = float(np.median(v))
    return {"pairs": len(pairs), "sampson_px": out}


def lens(args) -> None:
    ks = [0.0, -0.05, -0.1, -0.15]
    edges = lens_edges(args.root, ks)
    for k in ks:
        alone = edges["colour_lens_only"].get(k)
        print(f"k1 {k:+.2f}: edge score, both lenses {edges['both_lenses'][k]:.4f}"
              + (f", colour lens alone {alone:.4f}" if alone is not None else ""))
    samp = lens_sampson(args.root, [510, 525, 540, 555], ks + [-0.2])
    for h, by_f in samp["sampson_px"].items():
        for f, by_k in by_f.items():
            print(f"frames {h}, f {f:.0f}: median Sampson (px) " + "  ".join(f"k1 {k:+.2f} {v:.3f}" for k, v in by_k.items()))
    _harness.write_json(args.out.with_name("calibrate_7scenes_lens.json"), {"edge_score": edges, **samp})


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--root", type=Path, default=_harness.SEVEN_SCENES)
    p.add_argument("--focal", type=float, default=COLOR_INTRINSICS[0], help="focal length of the registration search")
    p.add_argument("--out", type=Path, default=_harness.OUTPUTS / "calibrate_7scenes.json")
    p.add_argument("--self-calibration", action="store_true", help="only the focal length from the images alone")
    p.add_argument("--lens", action="store_true", help="only the lenses' radial distortion (edges, epipolar)")
    args = p.parse_args()
    if args.lens:
        return lens(args)
    seq = SevenScenesSequence(args.root, sensor="mono", intrinsics=[585, 585, 320, 240], **RAW)
    if args.self_calibration:
        pairs = epipolar_pairs(seq, step=15, gap=20) + epipolar_pairs(seq, step=15, gap=40)
        gap = self_calibration(pairs, list(range(450, 651, 15)))
        for f, g in gap.items():
            print(f"focal {f:.0f}: mean singular-value gap of K^T F K {g:.5f}")
        _harness.write_json(args.out.with_name("calibrate_7scenes_self.json"),
                            {"pairs": len(pairs), "singular_value_gap_by_focal": gap, "best_focal": min(gap, key=gap.get)})
        return
    focal = focal_search(epipolar_pairs(seq), [500, 510, 515, 520, 525, 530, 540, 560, 585])
    for f, e in focal.items():
        print(f"focal {f:.0f}: median Sampson error {e:.3f} px")
    f_best = min(focal, key=focal.get)
    reg = registration_search(edge_frames(raw_frames(args.root)), args.focal)
    print(f"depth -> colour at f={args.focal:.0f}: tx {reg['tx_m'] * 100:.1f} cm, ty {reg['ty_m'] * 100:.1f} cm, "
          f"cx {reg['cx']:.0f}, cy {reg['cy']:.0f}; edge score {reg['unregistered_score']:.3f} unregistered -> {reg['score']:.3f}")  # fmt: skip
    _harness.write_json(args.out, {"sampson_px_by_focal": focal, "sampson_best_focal": f_best, "registration_focal": args.focal, "registration": reg})


if __name__ == "__main__":
    main()
