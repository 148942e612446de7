"""Benchmark the ORB frontend: tracking FPS, local-mapping and local-BA time per keyframe.

    python bench/tracking.py                     # synthetic loop, TUM sample, 7-Scenes RGB-D + mono
    python bench/tracking.py --sequences 7scenes_rgbd --runs 3
    python bench/tracking.py --runs 5 --frames 120 --features 1500

The 7-Scenes runs (../shared/data/7scenes_redkitchen_0000_0599, skipped when absent) use the
frontend exactly as `segs.track +experiment=seven_scenes_{rgbd,mono}` builds it (defaults only).
Per run and sequence the frontend processes every frame single-threaded (deterministic); the
figures are medians over frames (keyframes for mapping), then the median over --runs repeated
runs. Frames are decoded outside the timing. "tracking" = ORB extraction + depth lookup +
tracking of one frame (what ORB-SLAM's tracking thread does), wall clock and process CPU time
(the CPU time is what the frame costs without other jobs' load; it includes OpenCV's worker
threads); "end-to-end" = frames / total process() time single-threaded (tracking, local mapping
and loop closing in one thread); "threaded" = the same with local mapping and loop closing in a
background thread and bundle adjustment in a child process (gtsam holds the GIL), i.e. the
real-time mode (its keyframes are mapped after process() returns and a keyframe is refused while
the mapping queue is full; its FPS is given without and with the backlog finish() drains, beside
its keyframes and ATE). JSON: outputs/bench/tracking.json.
"""
from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

import _harness

_harness.apply_process_settings()  # before torch loads

import numpy as np

from segs.config import slam_frontend
from segs.data.synthetic import SyntheticSequence
from segs.data.tum import TumSequence
from segs.trajectory import ate

ROOT = _harness.ROOT


def one_run(seq, sensor: str, make_frontend, threaded: bool) -> dict:
    """Feed every frame of seq to a new frontend; only process() and finish() are timed (frames
    are decoded outside the timing)."""
    fe = make_frontend(threaded)
    process_s, cpu_s = 0.0, 0.0
    for i in range(len(seq)):
        f = seq[i]
        t0, c0 = time.perf_counter(), time.process_time()
        fe.process(f)
        process_s += time.perf_counter() - t0
        cpu_s += time.process_time() - c0
    t0 = time.perf_counter()
    fe.finish()
    finish_s = time.perf_counter() - t0
    t = {k: np.array(v) * 1e3 for k, v in fe.times.items()}
    traj = fe.trajectory()
    res = ate(seq.timestamps, traj, seq.gt_poses, "sim3" if sensor == "mono" else "se3")
    med = lambda a: float(np.median(a)) if len(a) else float("nan")  # noqa: E731
    return {
        "features_ms": med(t["features"]),
        "tracking_ms": med(t["track"]),
        "tracking_p90_ms": float(np.percentile(t["track"], 90)),
        "tracking_cpu_ms": med(t["track_cpu"]),
        "mapping_ms_per_kf": med(t["mapping"]),
        "local_ba_ms_per_kf": med(np.array(fe.local_mapping.ba_times) * 1e3),
        "loop_ms_per_kf": med(t["loop"]),
        "end_to_end_fps": len(seq) / process_s,
        # threaded: process() returns before its keyframes are mapped; finish() drains the backlog
        "end_to_end_fps_with_finish": len(seq) / (process_s + finish_s),
        "end_to_end_cpu_ms_per_frame": 1e3 * cpu_s / len(seq),
        "finish_s": finish_s,
        "keyframes": len(fe.keyframe_frames()),
        "tracked": len(traj),
        "frames": len(seq),
        "lost_frames": len(fe.lost_frames()),
        "ate_cm": None if res["rmse"] is None else 100 * res["rmse"],
        "ate_scale": res.get("scale"),
    }


def bench(name, seq, sensor, make_frontend, runs, threaded_too=True) -> dict:
    """Median over `runs` single-thread runs (and threaded runs: end-to-end FPS only)."""
    rows = [one_run(seq, sensor, make_frontend, False) for _ in range(runs)]
    out = _harness.medians(rows)
    out["ate_cm_runs"] = [r["ate_cm"] for r in rows]
    out["tracking_fps"] = 1e3 / out["tracking_ms"]
    out["tracking_fps_cpu"] = 1e3 / out["tracking_cpu_ms"]
    if threaded_too:
        th = [one_run(seq, sensor, make_frontend, True) for _ in range(runs)]
        out["threaded_fps"] = statistics.median([r["end_to_end_fps"] for r in th])
        out["threaded_fps_with_finish"] = statistics.median([r["end_to_end_fps_with_finish"] for r in th])
        out["threaded_runs"] = th
    out["runs"] = runs
    print(f"{name}: tracking {out['tracking_ms']:.1f} ms/frame ({out['tracking_fps']:.1f} FPS; "
          f"CPU {out['tracking_cpu_ms']:.1f} ms = {out['tracking_fps_cpu']:.1f} FPS; "
          f"features {out['features_ms']:.1f} ms), mapping {out['mapping_ms_per_kf']:.0f} ms/kf "
          f"(local BA {out['local_ba_ms_per_kf']:.0f} ms), end-to-end {out['end_to_end_fps']:.1f} FPS "
          f"({out['end_to_end_cpu_ms_per_frame']:.0f} ms CPU/frame)"
          + (f", threaded {out['threaded_fps']:.1f} FPS ({out['threaded_fps_with_finish']:.1f} with the backlog drained "
             f"in finish; {th[0]['keyframes']} kfs, ATE {th[0]['ate_cm']:.2f} cm)" if threaded_too else "")
          + f"; {out['keyframes']} kfs, {out['tracked']}/{out['frames']} tracked, ATE {out['ate_cm']:.2f} cm",
          flush=True)
    return out


def frontend_factory(camera, sensor: str, **kwargs):
    """threaded -> a new OrbFrontend with the frontend defaults and `kwargs` groups."""
    return lambda threaded: slam_frontend(camera, sensor, threaded=threaded, **kwargs)


def experiment(name: str, overrides: list[str]):
    """(sequence, threaded -> frontend) exactly as `segs.track +experiment=NAME OVERRIDES` builds them."""
    from segs.config import compose, instantiate, make_sequence

    cfg = compose([f"+experiment={name}", *overrides], output_dir="/tmp/segs_bench_tracking")
    seq = make_sequence(cfg.data)
    return seq, lambda threaded: instantiate(cfg.slam, threaded=threaded)(camera=seq.camera, sensor=seq.sensor)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--frames", type=int, default=90, help="frames of the synthetic loop")
    ap.add_argument("--features", type=int, default=1500)
    ap.add_argument("--sequences", nargs="+", default=["synthetic", "tum", "7scenes_rgbd", "7scenes_mono"],
                    choices=["synthetic", "tum", "7scenes_rgbd", "7scenes_mono"])
    ap.add_argument("--seven-scenes", default=str(_harness.SEVEN_SCENES))
    ap.add_argument("--override", nargs="*", default=[], help="extra config overrides for the 7-Scenes runs")
    ap.add_argument("--out", default=str(_harness.OUTPUTS / "tracking.json"))
    a = ap.parse_args()
    results = {**_harness.record(), "features": a.features}
    if "synthetic" in a.sequences:
        syn = SyntheticSequence(sensor="rgbd", n_frames=a.frames, width=640, height=480, trajectory="loop", seed=0)
        results["synthetic_rgbd_640"] = bench("synthetic RGB-D 640x480", syn, "rgbd",
                                              frontend_factory(syn.camera, "rgbd", features={"n_features": a.features}), a.runs)
    if "tum" in a.sequences:
        tum = TumSequence(ROOT / "datasets" / "tum_fr3_cabinet_kf", sensor="rgbd")
        feats = {"n_features": a.features, "fast_threshold": 7, "min_fast_threshold": 3}
        results["tum_cabinet_rgbd_640"] = bench("TUM fr3/cabinet kf RGB-D 640x480", tum, "rgbd",
                                                frontend_factory(tum.camera, "rgbd", features=feats), a.runs, threaded_too=False)
    for sensor in ("rgbd", "mono"):
        if f"7scenes_{sensor}" not in a.sequences:
            continue
        if not Path(a.seven_scenes).is_dir():
            print(f"7-Scenes frames not found at {a.seven_scenes}: skipped")
            continue
        seq, make = experiment(f"seven_scenes_{sensor}", [f"data.root={a.seven_scenes}"] + a.override)
        results[f"7scenes_{sensor}"] = bench(f"7-Scenes redkitchen {len(seq)} frames, {sensor}, 640x480, defaults", seq,
                                             sensor, make, a.runs)
    results["machine"]["load_avg_end"] = _harness.load_average()
    _harness.write_json(a.out, results)
    print(f"-> {a.out} (load average {results['machine']['load_avg'][0]:.1f} -> "
          f"{results['machine']['load_avg_end'][0]:.1f} on {os.cpu_count()} cores)")


if __name__ == "__main__":
    main()
