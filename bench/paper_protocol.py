"""The paper's protocol timed end to end: `python -m segs.train` on the 7-Scenes frames (640x480,
full size throughout (`mapping.num_downscales=0`; the experiment's own default trains coarse to
fine), ORB RGB-D frontend, schedules sized to 30,000 iterations, keyframes train, every other frame
is a test view), with the GPU's utilisation sampled beside it.

    python bench/paper_protocol.py                             # CUDA: gsplat, 30,000 steps
    python bench/paper_protocol.py --minutes 5                 # training stopped after 5 minutes (trainer.max_time)
    python bench/paper_protocol.py --minutes 5 --extra slam_mode=process mapping.compile=false
    python bench/paper_protocol.py --device cpu --steps 3000   # the CPU run of docs/performance.md

The run is the command a user types, in a process of its own; its log goes to <run dir>/command.log.
Where `nvidia-smi` answers, the GPU's utilisation and memory are read every second. Writes
outputs/bench/paper_protocol.json (the command, the machine, the run's metrics.json figures, the
wall time per step and the minutes 30,000 steps take at that rate) and prints one summary line; a
run that fails writes no JSON and exits with its status.
"""
from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

import _harness

PAPER_STEPS = 30_000  # the paper's iterations
KEYS = ("psnr", "ssim", "lpips", "test_views", "ate_rmse_m", "frames", "frames_tracked", "keyframes", "iterations",
        "scheduled_iterations", "mapping_time_s", "wall_time_s", "iteration_ms_median", "anchors", "gaussians", "model_mb",
        "peak_rss_mb")  # fmt: skip


def command(experiment: str, device: str, steps: int, minutes: float | None, run_dir: Path, extra: list[str]) -> list[str]:
    """The segs.train command of the protocol on `device` ("cuda" or "cpu")."""
    cmd = [sys.executable, "-m", "segs.train", f"+experiment={experiment}", f"trainer.max_steps={steps}",
           "mapping.num_downscales=0", "eval.save_renders=0", f"hydra.run.dir={run_dir}"]  # fmt: skip
    if device == "cuda":
        cmd += ["raster.backend=cuda", "trainer.accelerator=gpu"]
    if minutes is not None:
        total = int(round(minutes * 60))
        cmd.append(f"trainer.max_time=00:{total // 3600:02d}:{total % 3600 // 60:02d}:{total % 60:02d}")
    return cmd + list(extra)


class GpuSampler:
    """nvidia-smi's utilisation.gpu (%) and memory.used (MiB), once a second, in a thread."""

    def __init__(self):
        self.busy: list[float] = []
        self.memory: list[float] = []
        self._proc: subprocess.Popen | None = None
        self._thread: threading.Thread | None = None

    def start(self) -> bool:
        if shutil.which("nvidia-smi") is None:
            return False
        self._proc = subprocess.Popen(["nvidia-smi", "--query-gpu=utilization.gpu,memory.used", "--format=csv,noheader,nounits",
                                       "-l", "1"], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)  # fmt: skip
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()
        return True

    def _read(self) -> None:
        for line in self._proc.stdout:
            parts = [p.strip() for p in line.split(",")]
            if len(parts) >= 2 and all(p.replace(".", "", 1).isdigit() for p in parts[:2]):
                self.busy.append(float(parts[0]))
                self.memory.append(float(parts[1]))

    def stop(self) -> dict:
        if self._proc is not None:
            self._proc.terminate()
            self._proc.wait(timeout=10)
            self._thread.join(timeout=10)
        if not self.busy:
            return {"gpu_samples": 0}
        return {"gpu_samples": len(self.busy), "gpu_busy_mean_pct": statistics.fmean(self.busy), "gpu_busy_max_pct": max(self.busy),
                "gpu_memory_max_mib": max(self.memory)}  # fmt: skip


def run(cmd: list[str], run_dir: Path) -> tuple[int, float]:
    """Runs cmd with its output in run_dir/command.log; -> (exit status, wall seconds)."""
    run_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    with open(run_dir / "command.log", "w") as log:
        status = subprocess.call(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=_harness.ROOT)
    return status, time.perf_counter() - t0


def summary(metrics: dict, wall_s: float) -> dict:
    """The protocol's figures from a run's metrics.json and the command's wall seconds."""
    row = {k: metrics.get(k) for k in KEYS}
    row["command_wall_s"] = wall_s
    steps, mapping = metrics.get("iterations") or 0, metrics.get("mapping_time_s") or 0.0
    row["wall_ms_per_step"] = 1000.0 * mapping / steps if steps else None
    row["minutes_for_paper_steps"] = mapping / steps * PAPER_STEPS / 60.0 if steps else None
    prov = metrics.get("provenance", {})
    row.update({k: prov.get(k) for k in ("slam_mode", "raster_backend", "device", "compiled_step_code")})
    return row


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--experiment", default="seven_scenes_rgbd", help="+experiment=NAME")
    p.add_argument("--device", choices=("cuda", "cpu"), default="cuda")
    p.add_argument("--steps", type=int, default=PAPER_STEPS, help="trainer.max_steps (schedules are sized to it)")
    p.add_argument("--minutes", type=float, default=None, help="stop training after this many minutes (trainer.max_time)")
    p.add_argument("--extra", nargs="*", default=[], help="more overrides, e.g. slam_mode=process")
    p.add_argument("--run-dir", default=str(_harness.ROOT / "outputs" / "paper_protocol"))
    p.add_argument("--out", default=str(_harness.OUTPUTS / "paper_protocol.json"))
    args = p.parse_args()
    run_dir = Path(args.run_dir)
    if (run_dir / "metrics.json").exists():
        (run_dir / "metrics.json").unlink()  # a finished run's figures are never read as this run's
    cmd = command(args.experiment, args.device, args.steps, args.minutes, run_dir, args.extra)
    print(" ".join(cmd[1:]), flush=True)
    gpu = GpuSampler()
    sampled = args.device == "cuda" and gpu.start()
    status, wall = run(cmd, run_dir)
    gpu_row = gpu.stop() if sampled else {}
    metrics_path = run_dir / "metrics.json"
    if status != 0 or not metrics_path.is_file():
        tail = (run_dir / "command.log").read_text(errors="replace")[-3000:]
        raise SystemExit(f"bench/paper_protocol.py: the run failed (exit {status}); {run_dir / 'command.log'} ends:\n{tail}")
    row = {**summary(json.loads(metrics_path.read_text()), wall), **gpu_row}
    _harness.write_json(args.out, {**_harness.record(), "args": vars(args), "command": cmd[1:], "result": row})
    ate = "n/a" if row["ate_rmse_m"] is None else f"{100 * row['ate_rmse_m']:.2f} cm"
    busy = f", GPU busy {row['gpu_busy_mean_pct']:.0f} % (max {row['gpu_busy_max_pct']:.0f})" if row.get("gpu_samples") else ""
    print(f"{row['iterations']} of {args.steps} steps in {row['mapping_time_s']:.1f} s of mapping ({row['wall_ms_per_step']:.1f} ms "
          f"per step; {PAPER_STEPS} steps: {row['minutes_for_paper_steps']:.1f} min), {wall:.0f} s for the command; "
          f"PSNR {row['psnr']:.2f} dB, SSIM {row['ssim']:.3f} on {row['test_views']} views, ATE {ate}, "
          f"{row['anchors']} anchors{busy}")  # fmt: skip


if __name__ == "__main__":
    main()
