"""What keeps the 7-Scenes RGB-D ATE where it is: two ground-truth effects tested on one trajectory.

The 7-Scenes ground truth is the depth camera's KinectFusion track; the reader turns it into the
colour camera's with the measured depth->colour offset (segs.data.seven_scenes.DEPTH_TO_COLOR).
Two ways that conversion could leave a floor under the ATE, each measured on a trajectory of
`segs.track +experiment=seven_scenes_rgbd` (TUM file, frame i at i / 30 s):

- the lever arm: the colour centre = depth centre + R_depth t_dc. ATE (SE(3) alignment, RMSE of
  centres) without it, with the reader's, and with t_dc fitted jointly with the alignment (three
  more free parameters: an upper bound on what a better offset could give);
- time: the ground truth read at frame i + d (linear interpolation of centres), d in frames.

    python bench/ate_diagnostics.py                       # tracks the 600 frames first (defaults)
    python bench/ate_diagnostics.py --trajectory outputs/track/<run>/trajectory.txt

JSON: outputs/bench/ate_diagnostics.json.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from segs.data.base import DepthRegistration
from segs.data.seven_scenes import DEPTH_INTRINSICS, DEPTH_TO_COLOR, find_sequence, read_pose
from segs.slam.geometry import umeyama

ROOT = Path(__file__).resolve().parents[1]
SEVEN_SCENES = ROOT.parent / "shared" / "data" / "7scenes_redkitchen_0000_0599"
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


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--trajectory", type=Path, default=None, help="a segs.track trajectory.txt (default: track first)")
    p.add_argument("--root", type=Path, default=SEVEN_SCENES, help="the 7-Scenes folder the trajectory was tracked on")
    p.add_argument("--offsets", type=float, nargs="+", default=[-1.0, -0.5, -0.25, 0.0, 0.25, 0.5, 1.0])
    p.add_argument("--out", type=Path, default=ROOT / "outputs" / "bench" / "ate_diagnostics.json")
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
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(res, indent=1))
    print(f"ATE with the reader's lever arm {res['reader_lever_cm']} cm: {res['ate_cm_reader']:.2f} cm; "
          f"without: {res['ate_cm_no_lever']:.2f} cm; lever arm fitted ({res['fitted_lever_cm']} cm): "
          f"{res['ate_cm_fitted_lever']:.2f} cm")
    print("time offset (frames) -> ATE: " + ", ".join(f"{o['frames']:+g}: {o['ate_cm']:.2f} cm" for o in res["time_offsets"]))


if __name__ == "__main__":
    main()
