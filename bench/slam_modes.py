"""Whole-run wall time of `segs.train` with SLAM and mapping interleaved, side by side in two
processes, and live (issue 13 item 2).

Runs `python -m segs.train +experiment=seven_scenes_rgbd` on the shared 7-Scenes frames once per
slam_mode (interleaved: one process, frames fed between training steps; process: the frontend
in its own process, every frame as fast as it tracks; live: its own process, frames at their
30 Hz timestamps, frames dropped while tracking is behind), same frames, resolution and
iterations, and reads each run's metrics.json: wall time of the whole run, mapping (fit) time,
tracking FPS, frames tracked / dropped, ATE, test-view PSNR. Prints one table; JSON:
outputs/bench/slam_modes.json.

    python bench/slam_modes.py --frames 0 300 --steps 1500 --downscale 2
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import _harness

_harness.apply_process_settings()  # before torch loads

ROOT = _harness.ROOT
SEVEN_SCENES = _harness.SEVEN_SCENES
KEYS = ("wall_time_s", "mapping_time_s", "tracking_fps", "frames", "frames_tracked", "frames_dropped_live",
        "keyframes", "ate_rmse_m", "psnr", "ssim", "iterations")


def run_mode(mode: str, args, out: Path) -> dict:
    cmd = [sys.executable, "-m", "segs.train", "+experiment=seven_scenes_rgbd", f"data.root={SEVEN_SCENES}",
           f"data.frames=[{args.frames[0]},{args.frames[1]}]", f"data.downscale={args.downscale}",
           f"trainer.max_steps={args.steps}", f"slam_mode={mode}", "eval.save_renders=0", "eval.write_ply=false",
           "callbacks.periodic_checkpoint.every_n_steps=0", "callbacks.slam_bridge.progress=false",
           f"hydra.run.dir={out / mode}"] + args.extra  # fmt: skip
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"segs.train slam_mode={mode} failed ({proc.returncode}):\n{proc.stderr[-2000:]}")
    m = json.loads((out / mode / "metrics.json").read_text())
    return {"mode": mode, "process_wall_s": wall, **{k: m.get(k) for k in KEYS}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, nargs=2, default=[0, 300])
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--downscale", type=float, default=2)
    ap.add_argument("--modes", nargs="+", default=["interleaved", "process", "live"])
    ap.add_argument("--extra", nargs="*", default=[], help="more overrides for every run")
    args = ap.parse_args()
    if not (SEVEN_SCENES / "seq").is_dir():
        raise SystemExit(f"bench/slam_modes.py: the 7-Scenes frames are not at {SEVEN_SCENES}")
    # a folder per invocation: segs.train refuses a run folder that already holds a finished run
    out = _harness.OUTPUTS / "slam_modes" / time.strftime("%Y-%m-%d_%H-%M-%S")
    rows = []
    for mode in args.modes:
        load = _harness.load_average()[0]
        rows.append({**run_mode(mode, args, out), "load_before": load, "load_after": _harness.load_average()[0]})
        r = rows[-1]
        print(f"{mode:12s} run {r['process_wall_s']:7.1f} s (metrics wall {r['wall_time_s']:.1f}, mapping {r['mapping_time_s']:.1f}) | "
              f"tracking {r['tracking_fps'] or 0:.1f} FPS, {r['frames_tracked']}/{r['frames']} tracked, "
              f"{r['frames_dropped_live']} dropped, {r['keyframes']} kfs | ATE {100 * (r['ate_rmse_m'] or float('nan')):.2f} cm | "
              f"PSNR {r['psnr']:.2f} dB | load {r['load_before']:.1f} -> {r['load_after']:.1f}", flush=True)  # fmt: skip
    _harness.write_json(_harness.OUTPUTS / "slam_modes.json", {"args": vars(args), **_harness.record(), "runs": rows})


if __name__ == "__main__":
    main()
