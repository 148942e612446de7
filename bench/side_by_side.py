"""Two versions of the ORB frontend timed side by side, so that both see the same machine.

    python bench/side_by_side.py --against /tmp/base/src                 # 7-Scenes RGB-D, 3 pairs
    python bench/side_by_side.py --against /tmp/base/src --sequence 7scenes_mono --pairs 5

A before / after comparison run one after the other measures the host as much as the code: on
this 2-core machine the same code ran 17.1 and 20.4 frames/s a few minutes apart (docs/
decisions/015-frontend-cpp-kernels.md). Here each pair starts two
worker processes at once, one with this checkout's `segs` and one with the `segs` of --against (a
`src` folder: a git worktree of the reference commit), each single-threaded (one OpenCV thread, one
BLAS / OpenMP thread: one core each). Both decode the frames first (outside the timing), wait at a
barrier, then feed every frame to a new frontend in the deterministic single-thread mode, as
`segs.track +experiment=...` builds it (defaults, --override added). Reported per pair and as the
median over pairs: whole-run seconds, the sums of the frontend's own timers (features, tracking,
local mapping, loop closing), keyframes and ATE, and the ratio this / reference. Absolute figures
are those of a machine shared by two runs; the ratio is the measurement. JSON:
outputs/bench/side_by_side.json.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import statistics
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SEVEN_SCENES = ROOT.parent / "shared" / "data" / "7scenes_redkitchen_0000_0599"
# sequence -> (experiment, overrides); "synthetic" is small and needs no data (used by the tests)
SEQUENCES = {
    "7scenes_rgbd": ("seven_scenes_rgbd", [f"data.root={SEVEN_SCENES}"]),
    "7scenes_mono": ("seven_scenes_mono", [f"data.root={SEVEN_SCENES}"]),
    "synthetic": ("synthetic", ["data.width=320", "data.height=240", "data.n_frames=30"]),
}
TIMERS = ("features", "track", "mapping", "loop")  # OrbFrontend.times, summed over the run
ONE_THREAD = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OMP_WAIT_POLICY": "PASSIVE"}


def worker(sequence: str, overrides: list[str]) -> None:
    """Child process: load the frames, report ready on stdout, wait for a line on stdin, run the
    frontend single-threaded and print one JSON line."""
    import time

    import cv2
    import numpy as np

    import segs
    from segs.config import compose, instantiate, make_sequence
    from segs.trajectory import ate

    cv2.setNumThreads(1)
    name, base = SEQUENCES[sequence]
    cfg = compose([f"+experiment={name}", *base, *overrides], output_dir="/tmp/segs_bench_side_by_side")
    seq = make_sequence(cfg.data)
    frames = [seq[i] for i in range(len(seq))]
    fe = instantiate(cfg.slam, threaded=False)(camera=seq.camera, sensor=seq.sensor)
    print("ready", flush=True)
    sys.stdin.readline()
    t0 = time.perf_counter()
    for f in frames:
        fe.process(f)
    fe.finish()
    total = time.perf_counter() - t0
    res = ate(seq.timestamps, fe.trajectory(), seq.gt_poses, "sim3" if seq.sensor == "mono" else "se3")
    out = {"src": str(Path(segs.__file__).resolve().parents[1]), "frames": len(frames), "total_s": total,
           "fps": len(frames) / total, "keyframes": len(fe.keyframe_frames()),
           "ate_cm": 100 * res["rmse"] if res else float("nan")}
    out.update({f"{k}_s": float(np.sum(fe.times[k])) for k in TIMERS})
    print(json.dumps(out), flush=True)


def commit_of(src: Path) -> str:
    """The git commit of the tree holding src (and '+changes' when it has local changes), or '?'."""
    def git(*args):
        return subprocess.run(["git", "-C", str(src), *args], capture_output=True, text=True).stdout.strip()
    rev = git("rev-parse", "--short", "HEAD")
    return (rev + ("+changes" if git("status", "--porcelain", "--untracked-files=no") else "")) if rev else "?"


def start(src: Path, sequence: str, overrides: list[str]) -> subprocess.Popen:
    env = {**os.environ, **ONE_THREAD, "PYTHONPATH": str(src)}
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", "--sequence", sequence, "--override", *overrides]
    return subprocess.Popen(cmd, env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)


def run_pair(srcs: dict[str, Path], sequence: str, overrides: list[str]) -> dict[str, dict]:
    """Both workers at once, released together once both have loaded their frames."""
    procs = {side: start(src, sequence, overrides) for side, src in srcs.items()}
    try:
        for side, p in procs.items():
            if p.stdout.readline().strip() != "ready":
                raise RuntimeError(f"{side} worker ({srcs[side]}) failed before the barrier (exit {p.wait()})")
        for p in procs.values():
            p.stdin.write("go\n")
            p.stdin.flush()
        out = {}
        for side, p in procs.items():
            line = p.stdout.readline()
            if p.wait() != 0 or not line:
                raise RuntimeError(f"{side} worker ({srcs[side]}) failed (exit {p.returncode})")
            out[side] = json.loads(line)
        return out
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.kill()


def summary(pairs: list[dict[str, dict]]) -> dict:
    """Medians over pairs per side, and this / reference of the medians."""
    keys = ["total_s", "fps", *[f"{k}_s" for k in TIMERS]]
    med = {side: {k: statistics.median(p[side][k] for p in pairs) for k in keys} for side in ("this", "reference")}
    ratio = {k: med["this"][k] / med["reference"][k] if med["reference"][k] else float("nan") for k in keys}
    return {"median": med, "ratio_this_over_reference": ratio,
            "total_ratio_per_pair": [p["this"]["total_s"] / p["reference"]["total_s"] for p in pairs]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--against", help="the reference's src folder (a worktree of the other commit)")
    ap.add_argument("--sequence", default="7scenes_rgbd", choices=sorted(SEQUENCES))
    ap.add_argument("--pairs", type=int, default=3)
    ap.add_argument("--override", nargs="*", default=[], help="extra config overrides (both sides)")
    ap.add_argument("--out", default=str(ROOT / "outputs" / "bench" / "side_by_side.json"))
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.worker:
        worker(a.sequence, a.override)
        return
    if not a.against:
        ap.error("--against SRC is required (the reference's src folder)")
    if a.pairs < 1:
        ap.error("--pairs must be at least 1")
    ref = Path(a.against).resolve()
    if not (ref / "segs" / "__init__.py").is_file():
        sys.exit(f"--against {a.against}: no segs package there (give the src folder of a checkout)")
    if a.sequence.startswith("7scenes") and not SEVEN_SCENES.is_dir():
        sys.exit(f"{SEVEN_SCENES}: 7-Scenes frames not found (use --sequence synthetic)")
    srcs = {"this": ROOT / "src", "reference": ref}
    pairs = []
    for i in range(a.pairs):
        pairs.append(run_pair(srcs, a.sequence, a.override))
        t, r = pairs[-1]["this"], pairs[-1]["reference"]
        print(f"pair {i + 1}/{a.pairs}: this {t['total_s']:.1f} s ({t['keyframes']} kfs, {t['ate_cm']:.2f} cm), "
              f"reference {r['total_s']:.1f} s ({r['keyframes']} kfs, {r['ate_cm']:.2f} cm): "
              f"{t['total_s'] / r['total_s']:.3f}x", flush=True)
    res = {"date": datetime.datetime.now().isoformat(timespec="seconds"), "sequence": a.sequence,
           "overrides": a.override, "machine": {"cpus": os.cpu_count(), "platform": platform.platform()},
           "this": {"src": str(srcs["this"]), "commit": commit_of(srcs["this"])},
           "reference": {"src": str(ref), "commit": commit_of(ref)}, "pairs": pairs, **summary(pairs)}
    ratio = res["ratio_this_over_reference"]
    print(f"{a.sequence}, {a.pairs} pairs side by side, this ({res['this']['commit']}) / reference "
          f"({res['reference']['commit']}), medians: whole run {ratio['total_s']:.3f}x, "
          + ", ".join(f"{k} {ratio[f'{k}_s']:.3f}x" for k in TIMERS))
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(res, indent=2))
    print(f"-> {a.out}")


if __name__ == "__main__":
    main()
