"""Every real sequence x sensor available, with defaults, through `python -m segs.track`: one table.

    python bench/real_sequences.py                      # every row, one at a time
    python bench/real_sequences.py --only kitti 7scenes_0000_0299_mono
    python bench/real_sequences.py --compare outputs/bench/real_sequences/before.json
    python bench/real_sequences.py --jobs 2             # two rows at a time (timings then share the CPU)
    python bench/real_sequences.py --only 7scenes --override "data.intrinsics=[585,585,320,240]"

Rows (each `python -m segs.track +experiment=... data.root=...`, nothing else overridden):
- 7-Scenes redkitchen frames 0-299 and 300-599 (`../shared/data/7scenes_redkitchen_0000_0599`),
  RGB-D and monocular (`seven_scenes_rgbd` / `seven_scenes_mono`, `data.frames=[a,b]`);
- the bundled TUM fr3/cabinet keyframe sample (`datasets/tum_fr3_cabinet_kf`, 58 frames,
  640x480), RGB-D and monocular (`tum_rgbd` / `tum_mono`);
- KITTI odometry, 51 frames of a drive (`../shared/data/kitti_odometry_51`), monocular
  (`kitti_mono`); beside it the two-view essential-matrix odometry of bench/mono_forward.py
  (unit-length steps, Sim(3)-aligned like segs) on the same frames;
- the bundled EuRoC V1_01 stereo pairs (`datasets/euroc_v101_micro`, `euroc_stereo`).
Sequences whose folder is absent are listed as skipped. The shared data folder is
`../shared/data` beside the checkout, or $SEGS_SHARED_DATA, or --shared-data.

Columns: frames tracked / frames, keyframes, ATE RMSE (evo; SE(3) for RGB-D and stereo, Sim(3)
for monocular), frames/s of the whole run's wall clock (reading, features, tracking, mapping;
`wall_fps` of tracking.json: a shared CPU makes it noisy). Monocular rows also give the step scale
(segs.trajectory.step_scale: estimated / true path length over every 5 consecutive steps after
the Sim(3) alignment; min and max relative to the median: 1.00 / 1.00 for no drift).
The runs are deterministic (single-threaded frontend): the accuracy columns repeat exactly.

--compare OLD.json prints each row's ATE after / before, flags rows worse by more than 10 %, and
the mean of the ratios (the rule for changing a default: no row worse by more than 10 % and the
mean ATE better). JSON: outputs/bench/real_sequences/<time>.json with the commit that ran, the
segs.track run folders in outputs/bench/real_sequences/<time>/.
"""
from __future__ import annotations

import argparse
import datetime
import json
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import _harness

_harness.apply_process_settings()  # before torch loads

import numpy as np

from mono_forward import two_view_odometry

ROOT = _harness.ROOT
SEVEN_SCENES = "7scenes_redkitchen_0000_0599"
KITTI = "kitti_odometry_51"


def rows(shared: Path) -> list[dict]:
    """Every row: name, sensor, data folder, segs.track overrides."""
    out = []
    for sensor in ("rgbd", "mono"):
        for a, b in ((0, 300), (300, 600)):
            out.append({"name": f"7scenes_{a:04d}_{b - 1:04d}_{sensor}", "sequence": f"7-Scenes redkitchen {a}-{b - 1}",
                        "sensor": sensor, "root": shared / SEVEN_SCENES,
                        "overrides": [f"+experiment=seven_scenes_{sensor}", f"data.frames=[{a},{b}]"]})  # fmt: skip
    for sensor in ("rgbd", "mono"):
        out.append({"name": f"tum_cabinet_{sensor}", "sequence": "TUM fr3/cabinet keyframes", "sensor": sensor,
                    "root": ROOT / "datasets" / "tum_fr3_cabinet_kf", "overrides": [f"+experiment=tum_{sensor}"]})  # fmt: skip
    out.append({"name": "kitti_mono", "sequence": "KITTI odometry 51 frames", "sensor": "mono", "root": shared / KITTI,
                "overrides": ["+experiment=kitti_mono"], "two_view": True})  # fmt: skip
    out.append({"name": "euroc_stereo", "sequence": "EuRoC V1_01 20 pairs", "sensor": "stereo",
                "root": ROOT / "datasets" / "euroc_v101_micro", "overrides": ["+experiment=euroc_stereo"]})  # fmt: skip
    return out


def track(row: dict, out: Path, extra: list[str]) -> dict:
    """One `python -m segs.track` run of a row (+ extra overrides) -> its tracking.json figures
    (+ the two-view baseline)."""
    run_dir = out / row["name"]
    cmd = [sys.executable, "-m", "segs.track", *row["overrides"], f"data.root={row['root']}", *extra,
           f"hydra.run.dir={run_dir}"]  # fmt: skip
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    result = {"name": row["name"], "command": " ".join(cmd[1:-1]), "seconds": time.perf_counter() - t0}
    if proc.returncode != 0:
        tail = (proc.stderr.strip().splitlines() or ["?"])[-1]
        return {**result, "error": f"exit {proc.returncode}: {tail}"}
    m = json.loads((run_dir / "tracking.json").read_text())
    result.update({k: m[k] for k in ("frames", "frames_tracked", "keyframes", "ate_rmse_m", "wall_fps", "step_scale")})
    if result["step_scale"]:
        result["step_scale"].pop("ratios", None)
    if row.get("two_view"):
        result["two_view"] = two_view(row)
    return result


def two_view(row: dict) -> dict:
    """bench/mono_forward.py's essential-matrix odometry (unit steps) on the row's sequence."""
    from segs.config import compose, make_sequence
    from segs.slam.config import group_from_yaml
    from segs.slam.features.extractor import OrbExtractor
    from segs.trajectory import ate, step_scale

    cfg = compose([*row["overrides"], f"data.root={row['root']}"], output_dir="/tmp/segs_bench_real_sequences")
    seq = make_sequence(cfg.data)
    traj, failed, _ = two_view_odometry((seq[i] for i in range(len(seq))), seq.camera.K,
                                        OrbExtractor.from_config(group_from_yaml("features")))  # fmt: skip
    scale = step_scale(seq.timestamps, traj, seq.gt_poses)
    scale.pop("ratios", None)
    return {"ate_rmse_m": ate(seq.timestamps, traj, seq.gt_poses, "sim3")["rmse"], "failed_steps": failed,
            "step_scale": scale}


def _cm(v) -> str:
    return "n/a" if v is None else f"{100 * v:.2f} cm"


def _scale(s) -> str:
    return "" if not s or s.get("median") is None else f"{s['min_rel']:.2f} / {s['max_rel']:.2f}"


def print_table(rows_: list[dict], results: dict[str, dict]) -> None:
    print("| sequence | sensor | frames tracked | keyframes | ATE | frames/s | step scale min / max (x median) |")
    print("|---|---|---|---|---|---|---|")
    for row in rows_:
        r = results.get(row["name"])
        if r is None:
            continue
        if "skipped" in r or "error" in r:
            print(f"| {row['sequence']} | {row['sensor']} | {r.get('skipped') or r['error']} | | | | |")
            continue
        print(f"| {row['sequence']} | {row['sensor']} | {r['frames_tracked']}/{r['frames']} | {r['keyframes']} | "
              f"{_cm(r['ate_rmse_m'])} | {r['wall_fps']:.1f} | {_scale(r['step_scale'])} |")  # fmt: skip
        if "two_view" in r:
            t = r["two_view"]
            print(f"| {row['sequence']}: two-view odometry | mono | {r['frames']}/{r['frames']} | | "
                  f"{_cm(t['ate_rmse_m'])} | | {_scale(t['step_scale'])} |")  # fmt: skip


def compare(results: dict[str, dict], old_path: Path) -> dict:
    """Each row's ATE after / before against an earlier JSON; rows worse by more than 10 %, mean ratio."""
    old = json.loads(old_path.read_text())["rows"]
    ratios, worse = {}, []
    for name, r in results.items():
        o = old.get(name, {})
        a, b = r.get("ate_rmse_m"), o.get("ate_rmse_m")
        if a is None or b is None:
            continue
        ratios[name] = a / b
        lost = r["frames_tracked"] < o["frames_tracked"]
        if a > 1.1 * b or lost:
            worse.append(name)
        print(f"  {name}: ATE {_cm(b)} -> {_cm(a)} ({a / b:.3f}x), tracked {o['frames_tracked']} -> "
              f"{r['frames_tracked']}{'  WORSE' if name in worse else ''}")  # fmt: skip
    mean = float(np.mean(list(ratios.values()))) if ratios else None
    print(f"mean ATE ratio after / before {mean:.3f} over {len(ratios)} rows; worse by > 10 % (or fewer frames): "
          f"{', '.join(worse) or 'none'}")  # fmt: skip
    return {"against": str(old_path), "ratios": ratios, "mean_ratio": mean, "worse": worse}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shared-data", type=Path, default=_harness.SHARED_DATA)
    ap.add_argument("--only", nargs="*", default=None, help="row names (prefixes) to run")
    ap.add_argument("--jobs", type=int, default=1, help="rows run at a time (default 1: timings not shared)")
    ap.add_argument("--compare", type=Path, default=None, help="an earlier JSON of this script")
    ap.add_argument("--override", nargs="*", default=[],
                    help="config overrides added to every selected row (measuring a candidate default)")
    ap.add_argument("--out", type=Path, default=None,
                    help="JSON path (default outputs/bench/real_sequences/<time>.json); run folders beside it")
    a = ap.parse_args()
    if a.jobs < 1:
        raise SystemExit("bench/real_sequences.py: --jobs must be at least 1")
    stamp = f"{datetime.datetime.now():%Y%m%d-%H%M%S}"
    # run folders beside the JSON: outputs/bench/real_sequences/<time>/<row>/ or <out without .json>/<row>/
    out = a.out.with_suffix("") if a.out else _harness.OUTPUTS / "real_sequences" / stamp
    selected = [r for r in rows(a.shared_data) if a.only is None or any(r["name"].startswith(p) for p in a.only)]
    results: dict[str, dict] = {}
    todo = []
    for row in selected:
        if not row["root"].is_dir():
            results[row["name"]] = {"name": row["name"], "skipped": f"skipped: {row['root']} is absent"}
        else:
            todo.append(row)
    record = _harness.record()  # the machine and the load before the runs, the code that runs
    with ThreadPoolExecutor(a.jobs) as pool:
        for row, r in zip(todo, pool.map(lambda row: track(row, out, a.override), todo)):
            results[row["name"]] = r
            ate_s = r.get("error") or _cm(r.get("ate_rmse_m"))
            print(f"{row['name']}: {r.get('frames_tracked', '-')}/{r.get('frames', '-')} tracked, ATE {ate_s} "
                  f"({r['seconds']:.0f} s)", flush=True)  # fmt: skip
    print()
    print_table(selected, results)
    record["machine"]["load_avg_end"] = _harness.load_average()
    record.update(jobs=a.jobs, overrides=a.override, rows=results)
    if a.compare:
        record["compare"] = compare(results, a.compare)
    path = _harness.write_json(a.out or out.with_suffix(".json"), record)
    print(f"-> {path} (commit {record['code']['commit']}{', modified' if record['code']['dirty'] else ''})")


if __name__ == "__main__":
    main()
