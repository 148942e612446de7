"""Benchmark the ORB frontend: tracking FPS, local-mapping and local-BA time per keyframe.

    python bench/tracking.py                     # 640x480 synthetic RGB-D loop + real TUM sample
    python bench/tracking.py --runs 5 --frames 120 --features 1500

Per run and sequence the frontend processes every frame single-threaded (deterministic); the
figures are medians over frames (keyframes for mapping), then the median over --runs repeated
runs. "tracking" = ORB extraction + depth lookup + tracking of one frame (what a tracking thread
does), wall clock and process CPU time (the CPU time is what the frame costs without other
jobs' load; it includes OpenCV's worker threads); "end-to-end" = frames / total process() time single-threaded (tracking, local mapping and
loop closing in one thread); "threaded" = frames / process() time with mapping in its background
thread (on 2 cores under load the GIL limits the overlap). JSON: outputs/bench/tracking.json.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from segs.data.synthetic import SyntheticSequence
from segs.data.tum import TumSequence
from segs.slam.orb import OrbFrontend
from segs.trajectory import ate

ROOT = Path(__file__).resolve().parents[1]


def one_run(seq, frames, sensor: str, features: dict, threaded: bool) -> dict:
    fe = OrbFrontend(seq.camera, sensor, features=features, threaded=threaded)
    t0 = time.perf_counter()
    for f in frames:
        fe.process(f)
    process_s = time.perf_counter() - t0
    fe.finish()
    t = {k: np.array(v) * 1e3 for k, v in fe.times.items()}
    traj = fe.trajectory()
    res = ate(seq.timestamps, traj, seq.gt_poses, "sim3" if sensor == "mono" else "se3")
    med = lambda a: float(np.median(a)) if len(a) else float("nan")
    return {
        "features_ms": med(t["features"]),
        "tracking_ms": med(t["track"]),
        "tracking_p90_ms": float(np.percentile(t["track"], 90)),
        "tracking_cpu_ms": med(t["track_cpu"]),
        "mapping_ms_per_kf": med(t["mapping"]),
        "local_ba_ms_per_kf": med(np.array(fe.mapper.ba_times) * 1e3),
        "loop_ms_per_kf": med(t["loop"]),
        "end_to_end_fps": len(frames) / process_s,
        "keyframes": len(fe.keyframe_frames()),
        "tracked": len(traj),
        "frames": len(frames),
        "ate_cm": None if res["rmse"] is None else 100 * res["rmse"],
    }


def bench(name, seq, sensor, features, runs, threaded_too=True) -> dict:
    frames = [seq[i] for i in range(len(seq))]  # decoded once, outside the timing
    rows = [one_run(seq, frames, sensor, features, False) for _ in range(runs)]
    out = {k: statistics.median([r[k] for r in rows]) if isinstance(rows[0][k], float) else rows[0][k]
           for k in rows[0]}
    out["tracking_fps"] = 1e3 / out["tracking_ms"]
    if threaded_too:
        out["threaded_fps"] = statistics.median(
            [one_run(seq, frames, sensor, features, True)["end_to_end_fps"] for _ in range(runs)])
    out["runs"] = runs
    print(f"{name}: tracking {out['tracking_ms']:.1f} ms/frame ({out['tracking_fps']:.1f} FPS; "
          f"CPU {out['tracking_cpu_ms']:.1f} ms; "
          f"features {out['features_ms']:.1f} ms), mapping {out['mapping_ms_per_kf']:.0f} ms/kf "
          f"(local BA {out['local_ba_ms_per_kf']:.0f} ms), end-to-end {out['end_to_end_fps']:.1f} FPS"
          + (f", threaded {out['threaded_fps']:.1f} FPS" if threaded_too else "")
          + f"; {out['keyframes']} kfs, {out['tracked']}/{out['frames']} tracked, ATE {out['ate_cm']:.2f} cm",
          flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--frames", type=int, default=90, help="frames of the synthetic loop")
    ap.add_argument("--features", type=int, default=1500)
    ap.add_argument("--out", default=str(ROOT / "outputs" / "bench" / "tracking.json"))
    a = ap.parse_args()
    results = {
        "date": datetime.datetime.now().isoformat(timespec="seconds"),
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": sys.version.split()[0],
                    "load_avg_1m": os.getloadavg()[0]},
        "features": a.features,
    }
    syn = SyntheticSequence(sensor="rgbd", n_frames=a.frames, width=640, height=480, trajectory="loop", seed=0)
    results["synthetic_rgbd_640"] = bench("synthetic RGB-D 640x480", syn, "rgbd", {"n_features": a.features}, a.runs)
    tum = TumSequence(ROOT / "datasets" / "tum_fr3_cabinet_kf", sensor="rgbd")
    results["tum_cabinet_rgbd_640"] = bench("TUM fr3/cabinet kf RGB-D 640x480", tum, "rgbd",
                                            {"n_features": a.features, "fast_threshold": 7,
                                             "min_fast_threshold": 3}, a.runs, threaded_too=False)
    results["machine"]["load_avg_1m_end"] = os.getloadavg()[0]
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(results, indent=2))
    print(f"-> {a.out} (load average {results['machine']['load_avg_1m']:.1f} -> "
          f"{results['machine']['load_avg_1m_end']:.1f} on {os.cpu_count()} cores)")


if __name__ == "__main__":
    main()
