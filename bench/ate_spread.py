"""How much one run's ATE says: the frontend on the same real frames from several first frames.

The frontend is deterministic, but a chaotic system: a change that moves a pose by 1e-8 (the
order of a floating-point sum) can change which frames become keyframes and move the ATE of the
600 7-Scenes frames by a few millimetres. This script tracks the shared 7-Scenes sequence as
`segs.track +experiment=seven_scenes_{sensor}` does (defaults plus --override), once per first
frame 0, 1, ..., --offsets - 1 (frames k..599), single-threaded, --jobs runs at a time, and
reports each run's ATE (evo; SE(3) for RGB-D, Sim(3) for monocular), keyframes and frames
tracked, and their mean / standard deviation / range. Compare settings by these, not by one run.

    python bench/ate_spread.py --offsets 6
    python bench/ate_spread.py --offsets 6 --override slam.local_mapping.ba_iterations_rgbd=[4,1]

JSON: outputs/bench/ate_spread/<time>.json (with the source folder and commit of the segs that ran).
"""
from __future__ import annotations

import argparse
import datetime
import statistics
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import _harness

_harness.apply_process_settings()  # before torch loads

SEVEN_SCENES = _harness.SEVEN_SCENES


def track(sensor: str, root: str, first: int, overrides: list[str]) -> dict:
    """One deterministic run from frame `first` -> {first, ate_cm, keyframes, tracked, frames}."""
    from segs.config import compose, instantiate, make_sequence
    from segs.trajectory import ate

    cfg = compose([f"+experiment=seven_scenes_{sensor}", f"data.root={root}", *overrides],
                  output_dir="/tmp/segs_bench_ate_spread")  # fmt: skip
    seq = make_sequence(cfg.data)
    n = len(seq)
    cfg = compose([f"+experiment=seven_scenes_{sensor}", f"data.root={root}", *overrides, f"data.frames=[{first},{n}]"],
                  output_dir="/tmp/segs_bench_ate_spread")  # fmt: skip
    seq = make_sequence(cfg.data)
    fe = instantiate(cfg.slam)(camera=seq.camera, sensor=seq.sensor)
    for i in range(len(seq)):
        fe.process(seq[i])
    fe.finish()
    traj = fe.trajectory()
    res = ate(seq.timestamps, traj, seq.gt_poses, "sim3" if sensor == "mono" else "se3")
    return {"first": first, "ate_cm": None if res["rmse"] is None else 100 * res["rmse"],
            "keyframes": len(fe.keyframe_frames()), "tracked": len(traj), "frames": len(seq)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sensor", default="rgbd", choices=("rgbd", "mono"))
    ap.add_argument("--offsets", type=int, default=6, help="first frames 0 .. offsets-1")
    ap.add_argument("--jobs", type=int, default=2, help="runs at a time (processes)")
    ap.add_argument("--override", nargs="*", default=[], help="config overrides, as on the segs.track command line")
    ap.add_argument("--seven-scenes", default=str(SEVEN_SCENES))
    a = ap.parse_args()
    if not (Path(a.seven_scenes) / "seq").is_dir():
        raise SystemExit(f"bench/ate_spread.py: the 7-Scenes frames are not at {a.seven_scenes}")
    if a.offsets < 1 or a.jobs < 1:
        raise SystemExit("bench/ate_spread.py: --offsets and --jobs must be at least 1")
    with ProcessPoolExecutor(a.jobs) as pool:
        futures = [pool.submit(track, a.sensor, a.seven_scenes, k, a.override) for k in range(a.offsets)]
        rows = []
        for f in futures:
            rows.append(f.result())
            r = rows[-1]
            ate_s = "lost" if r["ate_cm"] is None else f"{r['ate_cm']:.2f} cm"
            print(f"  first frame {r['first']}: {r['tracked']}/{r['frames']} tracked, {r['keyframes']} keyframes, "
                  f"ATE {ate_s}", flush=True)  # fmt: skip
    ates = [r["ate_cm"] for r in rows if r["ate_cm"] is not None]
    summary = {"mean_cm": statistics.mean(ates), "sd_cm": statistics.stdev(ates) if len(ates) > 1 else 0.0,
               "min_cm": min(ates), "max_cm": max(ates)} if ates else {}  # fmt: skip
    if summary:
        print(f"7-Scenes {a.sensor} {' '.join(a.override) or 'defaults'}: ATE over {len(ates)} first frames "
              f"mean {summary['mean_cm']:.2f} cm, sd {summary['sd_cm']:.2f}, range "
              f"{summary['min_cm']:.2f}-{summary['max_cm']:.2f} cm")  # fmt: skip
    path = _harness.OUTPUTS / "ate_spread" / f"{datetime.datetime.now():%Y%m%d-%H%M%S}.json"
    print(f"-> {_harness.write_json(path, {'args': vars(a), **_harness.record(), 'runs': rows, 'summary': summary})}")


if __name__ == "__main__":
    main()
