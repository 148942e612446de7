"""What keeps the 7-Scenes RGB-D ATE where it is: two ground-truth effects tested on one trajectory.

The 7-Scenes ground truth is the depth camera's KinectFusion track; the reader turns it into the
colour camera's with the measured depth->colour offset (segs.data.seven_scenes.DEPTH_TO_COLOR).
Two ways that conversion could leave a floor under the ATE, each measured on a trajectory of
`segs.track +experiment=seven_scenes_rgbd` (TUM file, frame i at i / 30 s):

- the lever arm: the colour centre = depth centre + R_depth t_dc. ATE (SE(3) alignment, RMSE of
  centres) without it, with the reader's, and with t_dc fitted jointly with the alignment (three
  more free parameters: an upper bound on what a better offset could give);
- time: the ground truth read at frame i + d (linear interpolation of centres), d in frames.

And one test of which trajectory the colour images agree with (--epipolar): for frame pairs d
frames apart, SIFT matches (features the ORB frontend never saw) kept by a RANSAC fundamental
matrix that knows neither trajectory, and the median Sampson distance of those matches under the
relative pose of the ground truth and of the estimate (translation direction and rotation only:
no scale, no alignment).

    python bench/ate_diagnostics.py                       # tracks the 600 frames first (defaults)
    python bench/ate_diagnostics.py --trajectory outputs/track/<run>/trajectory.txt
    python bench/ate_diagnostics.py --trajectory ... --epipolar 5 15 30 60

JSON: outputs/bench/ate_diagnostics.json.
"""
from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import _harness

_harness.apply_process_settings()  # before torch loads

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from segs.data.base import DepthRegistration
from segs.data.seven_scenes import DEPTH_INTRINSICS, DEPTH_TO_COLOR, SevenScenesSequence, find_sequence, read_pose
from segs.slam.geometry import fundamental, inv_se3, sampson_distance, umeyama

ROOT = _harness.ROOT
SEVEN_SCENES = _harness.SEVEN_SCENES
FPS = 30.0


def rmse(est: np.ndarray, ref: np.ndarray) -> float:
    """ATE RMSE (m) of centres est [N,3] against ref [N,3] after the best SE(3) alignment."""
    S = umeyama(est, ref, False)
    return float(np.sqrt((((est @ S[:3, :3].T + S[:3, 3]) - ref) ** 2).sum(1).mean()))


def colour_centres(T_depth: np.ndarray, lever: np.ndarray) -> np.ndarray:
    """Colour-camera centres [N,3] from depth-camera camera-to-world poses [N,4,4] and the colour
    centre in the depth camera's frame lever [3]."""
    return T_depth[:, :3, 3] + T_depth[:, :3, :3] @ lever


def reader_lever() -> np.ndarray:
    """The colour centre [3] (m) in the depth camera's frame, as the reader converts the ground truth."""
    return np.linalg.inv(DepthRegistration(DEPTH_INTRINSICS, DEPTH_TO_COLOR).T)[:3, 3]


def fitted_lever(est: np.ndarray, T_depth: np.ndarray, start: np.ndarray) -> tuple[float, np.ndarray]:
    """ATE with the lever arm fitted jointly with the alignment -> (rmse m, lever [3] m)."""
    def residual(x):
        return ((est @ Rotation.from_rotvec(x[:3]).as_matrix().T + x[3:6]) - colour_centres(T_depth, x[6:])).ravel()

    S = umeyama(est, colour_centres(T_depth, start), False)
    x0 = np.concatenate([Rotation.from_matrix(S[:3, :3]).as_rotvec(), S[:3, 3], start])
    x = least_squares(residual, x0).x
    return float(np.sqrt((residual(x).reshape(-1, 3) ** 2).sum(1).mean())), x[6:]


def diagnose(trajectory: Path, root: Path, offsets: list[float]) -> dict:
    est = np.loadtxt(trajectory, ndmin=2)
    if est.shape[1] != 8:
        raise SystemExit(f"ate_diagnostics: {trajectory}: expected TUM lines 'time tx ty tz qx qy qz qw'")
    idx = np.round(est[:, 0] * FPS).astype(int)
    seq = find_sequence(root, None)
    n = int(idx.max()) + 1
    T_all = np.stack([read_pose(seq / f"frame-{i:06d}.pose.txt") for i in range(n)])
    P, T = est[:, 1:4], T_all[idx]
    lever = reader_lever()
    fit, fitted = fitted_lever(P, T, lever)
    out = {"trajectory": str(trajectory), "frames": len(idx), "reader_lever_cm": (100 * lever).round(2).tolist(),
           "ate_cm_reader": 100 * rmse(P, colour_centres(T, lever)), "ate_cm_no_lever": 100 * rmse(P, T[:, :3, 3]),
           "ate_cm_fitted_lever": 100 * fit, "fitted_lever_cm": (100 * fitted).round(2).tolist(), "time_offsets": []}  # fmt: skip
    C = colour_centres(T_all, lever)
    for d in offsets:
        q = idx + d
        ok = (q >= 0) & (q <= n - 1)
        i0 = np.minimum(np.floor(q[ok]).astype(int), n - 2)
        w = (q[ok] - i0)[:, None]
        out["time_offsets"].append({"frames": d, "ate_cm": 100 * rmse(P[ok], (1 - w) * C[i0] + w * C[i0 + 1])})
    return out


def consistent_matches(grey_i: np.ndarray, grey_j: np.ndarray, sift, min_matches: int = 30):
    """SIFT matches (ratio 0.8) between two uint8 images that a RANSAC fundamental matrix (1 px)
    keeps -> (x_i [N,2], x_j [N,2], that F [3,3]), or None when fewer than min_matches survive."""
    ki, di = sift.detectAndCompute(grey_i, None)
    kj, dj = sift.detectAndCompute(grey_j, None)
    if di is None or dj is None or len(ki) < min_matches or len(kj) < min_matches:
        return None
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(di, dj, k=2)
    good = [m[0] for m in knn if len(m) == 2 and m[0].distance < 0.8 * m[1].distance]
    if len(good) < min_matches:
        return None
    xi = np.array([ki[m.queryIdx].pt for m in good])
    xj = np.array([kj[m.trainIdx].pt for m in good])
    cv2.setRNGSeed(0)
    F, mask = cv2.findFundamentalMat(xi, xj, cv2.FM_RANSAC, 1.0, 0.999)
    if F is None or F.shape != (3, 3) or mask is None or mask.sum() < min_matches:
        return None
    keep = mask.ravel().astype(bool)
    return xi[keep], xj[keep], F


def epipolar(trajectory: Path, root: Path, gaps: list[int], stride: int) -> list[dict]:
    """Per gap d: median over frame pairs (i, i + d), i every `stride` frames, of the median Sampson
    distance (px) of the pair's consistent SIFT matches under the ground truth's relative pose and
    under the estimate's; the same under the RANSAC fundamental matrix itself (the best minimal
    sample's, 7 free parameters: a scale for the matches' noise, not a floor, since it is not
    refined; on exact synthetic frames the true pose scores below it); and the share of pairs where
    the estimate's is the lower."""
    est = np.loadtxt(trajectory, ndmin=2)
    idx = np.round(est[:, 0] * FPS).astype(int)
    est_c2w = {int(i): _c2w(row[1:]) for i, row in zip(idx, est)}
    seq = SevenScenesSequence(root, sensor="rgbd")
    K, sift, grey = seq.camera.K, cv2.SIFT_create(), {}

    def image(i: int) -> np.ndarray:
        if i not in grey:
            grey[i] = cv2.cvtColor((seq[i].rgb * 255).round().astype(np.uint8), cv2.COLOR_RGB2GRAY)
        return grey[i]

    out = []
    for d in gaps:
        gt_med, est_med, fit_med = [], [], []
        for i in range(0, len(seq) - d, stride):
            j = i + d
            if i not in est_c2w or j not in est_c2w:
                continue
            m = consistent_matches(image(i), image(j), sift)
            if m is None:
                continue
            xi, xj, F_fit = m
            fit_med.append(float(np.median(sampson_distance(F_fit, xi, xj))))
            for poses, acc in ((seq.gt_poses, gt_med), (est_c2w, est_med)):
                F = fundamental(inv_se3(poses[i]), inv_se3(poses[j]), K)
                acc.append(float(np.median(sampson_distance(F, xi, xj))))
        g, e = np.array(gt_med), np.array(est_med)
        out.append({"gap_frames": d, "pairs": len(g), "sampson_px_gt": float(np.median(g)) if len(g) else None,
                    "sampson_px_est": float(np.median(e)) if len(e) else None,
                    "sampson_px_fit": float(np.median(fit_med)) if fit_med else None,
                    "est_lower_share": float((e < g).mean()) if len(g) else None})
    return out


def _c2w(tum: np.ndarray) -> np.ndarray:
    """[4,4] camera-to-world from a TUM row's tx ty tz qx qy qz qw."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(tum[3:7]).as_matrix()
    T[:3, 3] = tum[:3]
    return T


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--trajectory", type=Path, default=None, help="a segs.track trajectory.txt (default: track first)")
    p.add_argument("--root", type=Path, default=SEVEN_SCENES, help="the 7-Scenes folder the trajectory was tracked on")
    p.add_argument("--offsets", type=float, nargs="+", default=[-1.0, -0.5, -0.25, 0.0, 0.25, 0.5, 1.0])
    p.add_argument("--epipolar", type=int, nargs="*", default=[], help="frame gaps of the epipolar test (none: skipped)")
    p.add_argument("--stride", type=int, default=20, help="epipolar test: a pair starts every this many frames")
    p.add_argument("--out", type=Path, default=_harness.OUTPUTS / "ate_diagnostics.json")
    args = p.parse_args()
    if not args.root.is_dir():
        raise SystemExit(f"ate_diagnostics: the 7-Scenes frames are not at {args.root} (--root)")
    if args.trajectory is None:
        run = args.out.parent / "ate_diagnostics_run"
        subprocess.run([sys.executable, "-m", "segs.track", "+experiment=seven_scenes_rgbd", f"data.root={args.root}",
                        f"hydra.run.dir={run}"], check=True, cwd=ROOT)  # fmt: skip
        args.trajectory = run / "trajectory.txt"
    if not args.trajectory.is_file():
        raise SystemExit(f"ate_diagnostics: no trajectory file at {args.trajectory}")
    res = diagnose(args.trajectory, args.root, args.offsets)
    if args.epipolar:
        res["epipolar"] = epipolar(args.trajectory, args.root, args.epipolar, args.stride)
    _harness.write_json(args.out, res)
    print(f"ATE with the reader's lever arm {res['reader_lever_cm']} cm: {res['ate_cm_reader']:.2f} cm; "
          f"without: {res['ate_cm_no_lever']:.2f} cm; lever arm fitted ({res['fitted_lever_cm']} cm): "
          f"{res['ate_cm_fitted_lever']:.2f} cm")
    print("time offset (frames) -> ATE: " + ", ".join(f"{o['frames']:+g}: {o['ate_cm']:.2f} cm" for o in res["time_offsets"]))
    for e in res.get("epipolar", []):
        print(f"pairs {e['gap_frames']} frames apart ({e['pairs']}): median Sampson distance of consistent SIFT "
              f"matches {e['sampson_px_gt']:.3f} px under the ground truth, {e['sampson_px_est']:.3f} px under the "
              f"estimate (lower in {100 * e['est_lower_share']:.0f} % of pairs), {e['sampson_px_fit']:.3f} px under "
              "their own RANSAC fundamental matrix")


if __name__ == "__main__":
    main()
