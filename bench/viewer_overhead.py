"""How much longer a training run takes with the web viewer on and a browser connected.

    python bench/viewer_overhead.py [--steps 300] [--repeats 3] [--refresh 5] [--browser-nice 19] [KEY=VALUE ...]

Runs `python -m segs.train` (default: the bundled sample, eval off) alternately without the
viewer (viewer=off) and with it (viewer=on), repeated --repeats times (off, on, off, on, ...);
compares the fit time (metrics.json mapping_time_s: training steps, tracking beside them, the
viewer's snapshots) by the median of each side, and the CPU time of the whole training process
(less disturbed than wall time by other work on a shared host). Prints one line `viewer overhead: ...` and writes
the figures to --json.

Both sides have a headless Chromium (Debian's `chromium`) open at nice --browser-nice (default 19):
with viewer=on it opens the run's page as soon as the server is up and stays connected until the
run ends; with viewer=off it shows the same viewer's page of a finished run (`python -m segs.view`
of a first, uncounted run of the same command, served beside). The page renders continuously, in
software without a GPU (about one core here); in use that happens on the machine the page is
opened from (over the network / SSH), not on the training machine's cores. It is there on both
sides because the browser alone changes the training time on this host (it takes cores from
training even at nice 19, and a busy low-priority process also keeps the virtual CPUs from idling
between OpenMP waits: docs/performance.md "Web viewer"), so the difference is the live viewer's:
snapshots on the training thread, the drawing and sending threads, and the browser's work on each
update. --browser-nice 0 measures browsers competing with training at the same priority.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import resource
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

import _harness

_harness.apply_process_settings()  # before torch loads

import numpy as np

ROOT = _harness.ROOT
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
        try:
            urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=5).close()
            return True
        except OSError:
            time.sleep(0.2)
    return False


def reference_page(run_dir: Path, env: dict) -> tuple[subprocess.Popen, str]:
    """`python -m segs.view run_dir` in a process of its own: (process, URL of its page)."""
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "segs.view", str(run_dir), "--port", str(port)], cwd=ROOT, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    if not wait_port(port, proc):
        raise SystemExit(f"viewer_overhead: python -m segs.view {run_dir} did not serve")
    return proc, f"http://127.0.0.1:{port}"


def open_browser(url: str, nice: int) -> subprocess.Popen:
    profile = tempfile.mkdtemp(prefix="segs-bench-chromium-")
    return subprocess.Popen(
        ["nice", "-n", str(nice), CHROMIUM, "--headless=new", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
         "--disable-component-update", "--disable-sync", "--no-first-run", f"--user-data-dir={profile}", url],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip


def _children_cpu() -> float:
    """User + system CPU seconds of this process's children that have ended."""
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def one_run(out: Path, steps: int, viewer: bool, refresh: float, nice: int, extra: list[str], reference: str | None) -> dict:
    """One training run; returns its fit / wall / CPU seconds and the viewer's snapshot log line.
    reference: the page the browser shows during a viewer=off run (None: no browser)."""
    port = free_port()
    cmd = [sys.executable, "-m", "segs.train", f"trainer.max_steps={steps}", *BASE, f"hydra.run.dir={out}", *extra]
    if viewer:
        cmd += ["viewer=on", f"viewer.port={port}", f"viewer.refresh_s={refresh}"]
    env = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE", "PYTHONPATH": str(ROOT / "src")}
    t0, cpu0 = time.perf_counter(), _children_cpu()
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    browser = None
    try:
        if not viewer and reference is not None:
            browser = open_browser(reference, nice)
        elif wait_port(port, proc):
            browser = open_browser(f"http://127.0.0.1:{port}", nice)
        _, err = proc.communicate()
        cpu = _children_cpu() - cpu0  # the training process only: the browser is still running
    finally:
        if browser is not None:
            browser.terminate()
            browser.wait(timeout=30)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"viewer_overhead: {' '.join(cmd)} failed ({proc.returncode}): {err.strip().splitlines()[-1:]}")
    metrics = json.loads((out / "metrics.json").read_text())
    log = (out / "train.log").read_text() if (out / "train.log").is_file() else ""
    found = re.search(r"viewer: (\d+) snapshots, median ([\d.]+) ms on the training thread, ([\d.]+) ms CPU drawing", log)
    if viewer and found is None:
        raise SystemExit(f"viewer_overhead: no browser connected to the run in {out} (no snapshot taken)")
    return {"viewer": viewer, "fit_s": metrics["mapping_time_s"], "wall_s": wall, "cpu_s": cpu, "iterations": metrics["iterations"],
            "snapshots": int(found.group(1)) if found else 0, "snapshot_ms_median": float(found.group(2)) if found else None,
            "draw_cpu_ms_median": float(found.group(3)) if found else None}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=300, help="training steps of each run (default 300)")
    parser.add_argument("--repeats", type=int, default=3, help="runs of each side, interleaved (default 3)")
    parser.add_argument("--refresh", type=float, default=5.0, help="viewer.refresh_s (default 5, conf/viewer/on.yaml)")
    parser.add_argument("--browser-nice", type=int, default=19, help="nice level of the browser (default 19; see the docstring)")
    parser.add_argument("--json", default=str(_harness.OUTPUTS / "viewer_overhead.json"),
                        help="where to write the figures (default outputs/bench/viewer_overhead.json)")
    parser.add_argument("overrides", nargs="*", help="more segs.train overrides (e.g. +experiment=seven_scenes_rgbd data.root=...)")
    args = parser.parse_args()
    if not Path(CHROMIUM).is_file():
        raise SystemExit(f"viewer_overhead: {CHROMIUM} not found (Debian: apt-get install chromium)")
    tmp = Path(tempfile.mkdtemp(prefix="segs-viewer-overhead-"))
    env = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE", "PYTHONPATH": str(ROOT / "src")}
    runs, view = [], None
    try:
        # a first run (not counted: it also warms the caches) whose page the viewer=off side shows
        first = one_run(tmp / "first", args.steps, False, args.refresh, args.browser_nice, args.overrides, None)
        print(f"  first run (not counted): fit {first['fit_s']:.1f} s", file=sys.stderr, flush=True)
        view, reference = reference_page(tmp / "first", env)
        for i in range(args.repeats):
            for viewer in (False, True):
                runs.append(one_run(tmp / f"{i}_{'on' if viewer else 'off'}", args.steps, viewer, args.refresh, args.browser_nice,
                                    args.overrides, reference))  # fmt: skip
                print(f"  run {len(runs)}: viewer {'on ' if viewer else 'off'} fit {runs[-1]['fit_s']:.1f} s, "
                      f"{runs[-1]['snapshots']} snapshots", file=sys.stderr, flush=True)
    finally:
        if view is not None:
            view.terminate()
            view.wait(timeout=30)
        shutil.rmtree(tmp, ignore_errors=True)
    off = float(np.median([r["fit_s"] for r in runs if not r["viewer"]]))
    on = float(np.median([r["fit_s"] for r in runs if r["viewer"]]))
    snap = [r["snapshot_ms_median"] for r in runs if r["viewer"]]
    cpu_off = float(np.median([r["cpu_s"] for r in runs if not r["viewer"]]))
    cpu_on = float(np.median([r["cpu_s"] for r in runs if r["viewer"]]))
    # the snapshots' own time on the training thread, a share of the fit time (median over the runs)
    share = float(np.median([r["snapshots"] * r["snapshot_ms_median"] / 1000 / r["fit_s"] for r in runs if r["viewer"]]))
    result = {"command": " ".join(sys.argv), "steps": args.steps, "repeats": args.repeats, "refresh_s": args.refresh,
              "browser_nice": args.browser_nice, "fit_s_median_off": off, "fit_s_median_on": on, "ratio": on / off,
              "cpu_s_median_off": cpu_off, "cpu_s_median_on": cpu_on, "cpu_ratio": cpu_on / cpu_off,
              "snapshot_ms_median": float(np.median(snap)), "snapshot_share_of_fit": share,
              "draw_cpu_ms_median": float(np.median([r["draw_cpu_ms_median"] for r in runs if r["viewer"]])),
              "host": socket.gethostname(), **_harness.record(), "runs": runs}  # fmt: skip
    _harness.write_json(args.json, result)
    sys.stdout.flush()
    print(f"viewer overhead: fit {on:.1f} s with the viewer and a browser on its page vs {off:.1f} s without (the browser on "
          f"a finished run's page; nice {args.browser_nice}), "
          f"ratio {on / off:.3f} ({100 * (on / off - 1):+.1f} %; median of {args.repeats} interleaved runs of {args.steps} steps, "
          f"snapshots: {result['snapshot_ms_median']:.0f} ms on the training thread every {args.refresh:g} s, {100 * share:.1f} % "
          f"of the fit, {result['draw_cpu_ms_median']:.0f} ms CPU drawing each; CPU time of the whole run {cpu_on:.1f} vs "
          f"{cpu_off:.1f} s, ratio {cpu_on / cpu_off:.3f}) -> {args.json}")


if __name__ == "__main__":
    main()
