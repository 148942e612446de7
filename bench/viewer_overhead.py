"""How much longer a training run takes with the web viewer on and a browser connected.

    python bench/viewer_overhead.py [--steps 300] [--repeats 3] [--refresh 5] [--browser-nice 19] [KEY=VALUE ...]

Runs `python -m segs.train` (default: the bundled sample, eval off) alternately without the
viewer (viewer=off) and with it (viewer=on) plus a headless Chromium (Debian's `chromium`) that
opens the page as soon as the server is up and stays connected until the run ends; repeats the
pair --repeats times (off, on, off, on, ...). Compares the fit time (metrics.json
mapping_time_s: training steps, tracking beside them, the viewer's snapshots) by the median of
each side. Prints one line `viewer overhead: ...` and writes the figures to --json.

The browser runs at nice --browser-nice (default 19): the 3D page renders continuously, in
software without a GPU (about one core here), which in use happens on the viewer's own machine
(the page is opened over the network / SSH), not on the training machine's cores; at nice 19 it
takes only cores the training leaves idle while it still receives every snapshot. --browser-nice 0
measures a browser competing with training for this machine's cores.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM = "/usr/bin/chromium"
BASE = ["logger=none", "eval.enabled=false", "callbacks.slam_bridge.progress=false", "~callbacks.progress_bar",
        "trainer.enable_progress_bar=false", "callbacks.periodic_checkpoint.every_n_steps=0"]  # fmt: skip


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_port(port: int, proc: subprocess.Popen, timeout: float = 300.0) -> bool:
    """Whether the server on port accepts connections before the run ends / the timeout."""
    end = time.monotonic() + timeout
    while time.monotonic() < end and proc.poll() is None:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return True
        time.sleep(0.2)
    return False


def one_run(out: Path, steps: int, viewer: bool, refresh: float, nice: int, extra: list[str]) -> dict:
    """One training run; returns its fit / wall seconds and the viewer's snapshot log line."""
    port = free_port()
    cmd = [sys.executable, "-m", "segs.train", f"trainer.max_steps={steps}", *BASE, f"hydra.run.dir={out}", *extra]
    if viewer:
        cmd += ["viewer=on", f"viewer.port={port}", f"viewer.refresh_s={refresh}"]
    env = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE", "PYTHONPATH": str(ROOT / "src")}
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    browser = None
    try:
        if viewer and wait_port(port, proc):
            profile = tempfile.mkdtemp(prefix="segs-bench-chromium-")
            browser = subprocess.Popen(
                ["nice", "-n", str(nice), CHROMIUM, "--headless=new", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--no-first-run", f"--user-data-dir={profile}",
                 f"http://127.0.0.1:{port}"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
        _, err = proc.communicate()
    finally:
        if browser is not None:
            browser.terminate()
            browser.wait(timeout=30)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"viewer_overhead: {' '.join(cmd)} failed ({proc.returncode}): {err.strip().splitlines()[-1:]}")
    metrics = json.loads((out / "metrics.json").read_text())
    log = (out / "train.log").read_text() if (out / "train.log").is_file() else ""
    found = re.search(r"viewer: (\d+) snapshots, median ([\d.]+) ms on the training thread", log)
    if viewer and found is None:
        raise SystemExit(f"viewer_overhead: no browser connected to the run in {out} (no snapshot taken)")
    return {"viewer": viewer, "fit_s": metrics["mapping_time_s"], "wall_s": wall, "iterations": metrics["iterations"],
            "snapshots": int(found.group(1)) if found else 0, "snapshot_ms_median": float(found.group(2)) if found else None}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=300, help="training steps of each run (default 300)")
    parser.add_argument("--repeats", type=int, default=3, help="runs of each side, interleaved (default 3)")
    parser.add_argument("--refresh", type=float, default=5.0, help="viewer.refresh_s (default 5, conf/viewer/on.yaml)")
    parser.add_argument("--browser-nice", type=int, default=19, help="nice level of the browser (default 19; see the docstring)")
    parser.add_argument("--json", default="viewer_overhead.json", help="where to write the figures (default viewer_overhead.json)")
    parser.add_argument("overrides", nargs="*", help="more segs.train overrides (e.g. +experiment=seven_scenes_rgbd data.root=...)")
    args = parser.parse_args()
    if not Path(CHROMIUM).is_file():
        raise SystemExit(f"viewer_overhead: {CHROMIUM} not found (Debian: apt-get install chromium)")
    tmp = Path(tempfile.mkdtemp(prefix="segs-viewer-overhead-"))
    runs = []
    try:
        for i in range(args.repeats):
            for viewer in (False, True):
                runs.append(one_run(tmp / f"{i}_{'on' if viewer else 'off'}", args.steps, viewer, args.refresh, args.browser_nice,
                                    args.overrides))  # fmt: skip
                print(f"  run {len(runs)}: viewer {'on ' if viewer else 'off'} fit {runs[-1]['fit_s']:.1f} s, "
                      f"{runs[-1]['snapshots']} snapshots", file=sys.stderr, flush=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    off = float(np.median([r["fit_s"] for r in runs if not r["viewer"]]))
    on = float(np.median([r["fit_s"] for r in runs if r["viewer"]]))
    snap = [r["snapshot_ms_median"] for r in runs if r["viewer"]]
    result = {"command": " ".join(sys.argv), "steps": args.steps, "repeats": args.repeats, "refresh_s": args.refresh,
              "browser_nice": args.browser_nice, "fit_s_median_off": off, "fit_s_median_on": on, "ratio": on / off,
              "snapshot_ms_median": float(np.median(snap)), "host": f"{socket.gethostname()}, {os.cpu_count()} CPUs",
              "runs": runs}  # fmt: skip
    Path(args.json).write_text(json.dumps(result, indent=2))
    print(f"viewer overhead: fit {on:.1f} s with the viewer and a browser (nice {args.browser_nice}) vs {off:.1f} s without, "
          f"ratio {on / off:.3f} ({100 * (on / off - 1):+.1f} %; median of {args.repeats} interleaved runs of {args.steps} steps, "
          f"snapshot {result['snapshot_ms_median']:.0f} ms on the training thread every {args.refresh:g} s) -> {args.json}")


if __name__ == "__main__":
    main()
