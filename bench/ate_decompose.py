"""What a 7-Scenes Sim(3) ATE is made of: one trajectory against the ground truth, and against
another estimate of the same frames.

    python bench/ate_decompose.py --trajectory outputs/track/<mono run>/trajectory.txt --frames 0 300
    python bench/ate_decompose.py --trajectory <mono>/trajectory.txt --reference <rgbd>/trajectory.txt

For a segs.track trajectory (TUM file, frame i at i / 30 s) of 7-Scenes frames [start, stop),
each part measured with the Sim(3) alignment of the monocular ATE (evo's Umeyama):
- the ATE, and its RMS per `--segment` frames (where along the sequence it comes from);
- the ATE of each `--window` frames aligned on their own, and that window's alignment scale over
  the whole trajectory's (a locally right trajectory has a small windowed ATE; a scale drift shows
  as window scales that differ);
- the rotation gain per camera axis: estimated / true relative rotation over `--lag` frames, least
  squares per component of the rotation vector in the camera frame (x tilt, y pan, z roll);
- the ATE once the ground-truth centres may move by a constant offset in the camera frame,
  fitted with the alignment (three more free parameters): the share of the error that a rotation
  about another centre explains (a hand-eye lever arm, or rotation traded for translation);
- with --reference (another estimate of the same frames, e.g. RGB-D, metric): the Sim(3) ATE of
  the trajectory against it and the window scales against it (the part the two estimates do not
  share: a monocular scale drift shows here, the ground truth's own disagreement with the images
  does not).
JSON: outputs/bench/ate_decompose.json.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import _harness

_harness.apply_process_settings()  # before torch loads

import numpy as np
from evo.core.geometry import umeyama_alignment
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from segs.data.seven_scenes import SevenScenesSequence
from segs.trajectory import read_tum

FPS = 30.0


def sim3_residuals(est: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, float]:
    """Residuals [N,3] (m) of centres est [N,3] after the best Sim(3) onto ref [N,3], and its scale."""
    r, t, s = umeyama_alignment(est.T, ref.T, True)
    return s * est @ r.T + t - ref, float(s)


def rms(d: np.ndarray) -> float:
    return float(np.sqrt((d ** 2).sum(-1).mean()))


def windows(est: np.ndarray, ref: np.ndarray, size: int, scale: float) -> list[dict]:
    """ATE (cm) of each `size` consecutive centres aligned on their own, and their scale / scale."""
    out = []
    for i in range(0, len(est) - size + 1, size):
        d, s = sim3_residuals(est[i:i + size], ref[i:i + size])
        out.append({"first": i, "ate_cm": 100 * rms(d), "scale_rel": s / scale})
    return out


def rotation_gain(est_c2w: np.ndarray, gt_c2w: np.ndarray, lag: int) -> list[float]:
    """Least-squares gain per camera axis of the estimated relative rotation vectors over `lag`
    frames against the true ones (NaN for an axis the truth never turns about); est_c2w, gt_c2w
    [N,4,4]."""
    ve, vg = [], []
    for k in range(len(est_c2w) - lag):
        for T, acc in ((est_c2w, ve), (gt_c2w, vg)):
            acc.append(Rotation.from_matrix((np.linalg.inv(T[k]) @ T[k + lag])[:3, :3]).as_rotvec())
    ve, vg = np.array(ve), np.array(vg)
    den = (vg ** 2).sum(0)
    return [float(vg[:, i] @ ve[:, i] / den[i]) if den[i] > 0 else float("nan") for i in range(3)]


def fitted_offset(est: np.ndarray, gt_c2w: np.ndarray) -> tuple[float, np.ndarray]:
    """Sim(3) ATE (m) of centres est [N,3] against the ground-truth centres moved by a constant
    offset in the camera frame, fitted jointly with the alignment -> (ATE, offset [3] m)."""
    def residual(x):
        return sim3_residuals(est, gt_c2w[:, :3, 3] + gt_c2w[:, :3, :3] @ x)[0].ravel()
    sol = least_squares(residual, np.zeros(3))
    return rms(sol.fun.reshape(-1, 3)), sol.x


def load(path: Path, start: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(sequence positions [M], c2w [M,4,4]) of a TUM trajectory of frames start + position."""
    t, c2w = read_tum(path)
    pos = np.round(t * FPS).astype(int) - start
    keep = (pos >= 0) & (pos < n)
    if keep.sum() < 3:
        raise SystemExit(f"ate_decompose: {path}: fewer than 3 poses in the frames (--frames)")
    return pos[keep], c2w[keep]


def decompose(args) -> dict:
    seq = SevenScenesSequence(args.root, "mono", frames=list(args.frames))
    pos, est = load(args.trajectory, args.frames[0], len(seq))
    gt = seq.gt_poses[pos]
    d, scale = sim3_residuals(est[:, :3, 3], gt[:, :3, 3])
    err = np.linalg.norm(d, axis=1)
    fit, offset = fitted_offset(est[:, :3, 3], gt)
    res = {"trajectory": str(args.trajectory), "frames": list(args.frames), "poses": len(pos),
           "ate_cm": 100 * rms(d), "scale": scale,
           "segment_rms_cm": [float(100 * np.sqrt((err[i:i + args.segment] ** 2).mean()))
                              for i in range(0, len(err), args.segment)],
           "windows": windows(est[:, :3, 3], gt[:, :3, 3], args.window, scale),
           "rotation_gain_xyz": rotation_gain(est, gt, args.lag),
           "ate_cm_fitted_offset": 100 * fit, "fitted_offset_cm": (100 * offset).round(2).tolist()}
    if args.reference is not None:
        rpos, ref = load(args.reference, args.frames[0], len(seq))
        common, ie, ir = np.intersect1d(pos, rpos, return_indices=True)
        a, b = est[ie, :3, 3], ref[ir, :3, 3]
        dr, sr = sim3_residuals(a, b)
        res["reference"] = {"trajectory": str(args.reference), "poses": len(common), "ate_cm": 100 * rms(dr),
                            "windows": windows(a, b, args.window, sr),
                            "rotation_gain_xyz": rotation_gain(est[ie], ref[ir], args.lag)}
    return res


def report(res: dict) -> None:
    print(f"Sim(3) ATE {res['ate_cm']:.2f} cm over {res['poses']} poses (alignment scale {res['scale']:.3f})")
    print("  RMS per segment (cm): " + " ".join(f"{x:.1f}" for x in res["segment_rms_cm"]))
    print("  windows aligned alone, ATE (cm): " + " ".join(f"{w['ate_cm']:.2f}" for w in res["windows"]))
    print("  windows' scale / the whole's:    " + " ".join(f"{w['scale_rel']:.3f}" for w in res["windows"]))
    print("  rotation gain est / true, camera x y z: " + " ".join(f"{g:.3f}" for g in res["rotation_gain_xyz"]))
    print(f"  with a fitted constant offset of the true centres {res['fitted_offset_cm']} cm (camera frame): "
          f"{res['ate_cm_fitted_offset']:.2f} cm")
    if "reference" in res:
        r = res["reference"]
        print(f"against the reference {r['trajectory']}: Sim(3) ATE {r['ate_cm']:.2f} cm over {r['poses']} poses")
        print("  windows' scale / the whole's:    " + " ".join(f"{w['scale_rel']:.3f}" for w in r["windows"]))
        print("  rotation gain / the reference's, x y z: " + " ".join(f"{g:.3f}" for g in r["rotation_gain_xyz"]))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--trajectory", type=Path, required=True, help="a segs.track trajectory.txt")
    p.add_argument("--reference", type=Path, default=None, help="another estimate of the same frames")
    p.add_argument("--root", type=Path, default=_harness.SEVEN_SCENES, help="the 7-Scenes folder tracked")
    p.add_argument("--frames", type=int, nargs=2, default=[0, 300], help="data.frames [start, stop) of the run")
    p.add_argument("--segment", type=int, default=25)
    p.add_argument("--window", type=int, default=50)
    p.add_argument("--lag", type=int, default=10)
    p.add_argument("--out", type=Path, default=_harness.OUTPUTS / "ate_decompose.json")
    args = p.parse_args()
    for path, what in ((args.root, "--root"), (args.trajectory, "--trajectory"), (args.reference, "--reference")):
        if path is not None and not path.exists():
            raise SystemExit(f"ate_decompose: {path} not found ({what})")
    res = decompose(args)
    _harness.write_json(args.out, {**res, **_harness.record()})
    report(res)


if __name__ == "__main__":
    main()
