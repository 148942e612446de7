"""What point_cloud.ply shows in a standard 3D-GS viewer, against the fit steps: test-view PSNR of
the exported Gaussians of a finished segs.train run (SEGS), as written with each number of
`eval.ply_fit_steps`, beside the map's own test-view PSNR.

    python bench/ply_fit.py RUN_DIR [--steps 0 100 300 500 1000] [--out outputs/bench/ply_fit.json]

Rebuilds the run's mapper from its checkpoint (as `python -m segs.view` does), reads its data, the
estimated trajectory and the test frames of its test_views.csv, then for every step count: the
fitted Gaussians (GaussianMapper.fitted_cloud; 0 = the first keyframe's decoding as it is), the
seconds the fit took, the Gaussians kept, and their test-view PSNR as a 3D-GS viewer draws them
(segs.evaluation.cloud_psnr); then what segs's own viewer draws from each test camera (the
Gaussians decoded for that camera, GaussianMapper.gaussians(w2c, camera), drawn the same way).
Prints a markdown table; writes the JSON with the machine and commit.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import _harness

_harness.apply_process_settings()  # before torch loads

import numpy as np  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run", type=Path, help="the folder of a finished segs.train run of SEGS (checkpoint, test_views.csv)")
    p.add_argument("--steps", type=int, nargs="+", default=[0, 100, 300, 500, 1000])
    p.add_argument("--out", type=Path, default=_harness.OUTPUTS / "ply_fit.json")
    args = p.parse_args(argv)

    from segs.evaluation import cloud_psnr
    from segs.view import load_mapper, load_sequence
    from segs.viewer.saved_run import read_run

    run = read_run(args.run)
    mapper, (sequence, why) = load_mapper(run), load_sequence(run)
    csv = args.run / "test_views.csv"
    if mapper is None or sequence is None or run.trajectory is None or not csv.is_file():
        sys.exit(f"{args.run}: needs a checkpoint, the run's data, trajectory.txt and test_views.csv ({why or 'missing'})")
    if not mapper.model.decodes_per_view:
        sys.exit(f"{args.run}: the map is written as its own parameters (not SEGS): there is nothing to fit")
    rows = [line.split(",") for line in csv.read_text().splitlines()[1:]]  # frame, psnr, ssim, lpips
    test, model_psnr = [int(r[0]) for r in rows], float(np.mean([float(r[1]) for r in rows]))
    trajectory = {idx: run.w2c_at(sequence.timestamps[idx]) for idx in test}
    rows = []
    for steps in sorted(args.steps):
        t0 = time.perf_counter()
        cloud = mapper.fitted_cloud(steps)
        seconds = time.perf_counter() - t0
        rows.append({"steps": steps, "fit_s": round(seconds, 2), "gaussians": len(cloud),
                     "psnr": round(cloud_psnr(mapper, cloud, sequence, trajectory, test), 3)})  # fmt: skip
        print(f"  {steps} steps: {rows[-1]['psnr']:.2f} dB, {len(cloud)} Gaussians, {seconds:.1f} s", flush=True)
    per_camera = float(np.mean([cloud_psnr(mapper, mapper.gaussians(trajectory[i], sequence.camera), sequence, trajectory, [i])
                                for i in test]))  # fmt: skip
    print(f"\n{args.run} ({len(test)} test views; the map itself: {model_psnr:.2f} dB; segs's viewer, decoded for each "
          f"test camera: {per_camera:.2f} dB), {_harness.short_commit()}\n")  # fmt: skip
    print("| fit steps | PLY test PSNR (3D-GS viewer) | Gaussians written | fit s |\n|---|---|---|---|")
    for r in rows:
        print(f"| {r['steps']} | {r['psnr']:.2f} | {r['gaussians']:,} | {r['fit_s']:.1f} |")
    _harness.write_json(args.out, {"run": str(args.run), "model_psnr": model_psnr, "camera_psnr": per_camera, "test_views": len(test),
                                   "rows": rows, **_harness.record()})  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
