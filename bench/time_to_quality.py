"""Time to quality: test-view PSNR / SSIM against wall-clock training seconds, SEGS vs plain 3D-GS.

For every dataset and method the run is built as `python -m segs.train` builds it
(segs.train.build: sequence, frontend, GaussianMapperModule, SlamBridge, Lightning trainer) and
trained; a training clock counts the wall-clock seconds of fit (frame feeding + steps). At each
mark (log spaced, --marks, up to --budget) the clock stops, every test view is rendered and
scored with the project's evaluation (segs.evaluation.render_test_views: PSNR, SSIM), and the
clock restarts, so evaluation is never counted (its seconds are recorded apart, eval_s).

Datasets (both with ground-truth poses, slam=known_poses, to isolate mapping speed):
- 7scenes: the shared real 7-Scenes redkitchen frames (../shared/data/7scenes_redkitchen_0000_0599;
  skipped with a message when absent), frames 100-249 at 320x240 (data.downscale=2), every 8th
  frame held out (eval.holdout_every=8) and the frames that do not become keyframes are test views;
- sample: the bundled TUM sample (+experiment=sample), its own 15 test views.
Every frame is fed to the frontend before the first step (min_initial_keyframes above the frame
count; counted by the clock), as an offline 3D-GS trainer has all images, so every mark scores
the same test views. Loggers, progress bars, image logging and checkpoints are off.

Schedule length: the LR / densification schedules scale with trainer.max_steps, which is, in
this order: --max-steps (every curve); with --pace-from JSON the steps the same curve reached in
that earlier output; else from a --warmup-s second warm-up of the same run (discarded):
steps/s of the warm-up's second half x (budget - feeding seconds). The warm-up sees the map
before it grows, so on a growing map it overestimates (decision 020:
neither 7-Scenes schedule was done at 10 minutes); the JSON records max_steps, the steps reached
and schedule_done per curve. A run that reaches max_steps before the budget ends there.

Each curve runs in its own process (peak RSS per curve). Output: outputs/bench/time_to_quality.json
(every point: method, dataset, seconds, steps, psnr, ssim, anchors, gaussians, peak_rss_mb,
eval_s), the chart docs/performance/time_to_quality.png and a markdown table on stdout.

    nice -n 5 python bench/time_to_quality.py --budget 600 --sample-budget 300
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

import _harness

_harness.apply_process_settings()  # before torch loads

import lightning as L

ROOT = _harness.ROOT
SEVEN_SCENES = _harness.SEVEN_SCENES
DATASETS = {
    "7scenes": ["+experiment=seven_scenes_rgbd", "slam=known_poses", f"data.root={SEVEN_SCENES}", "data.frames=[100,250]",
                "data.downscale=2", "eval.holdout_every=8"],
    "sample": ["+experiment=sample"],
}  # fmt: skip
# segs: the defaults of the dataset's experiment (the sample: coarse-to-fine; 7-Scenes: full size);
# segs_c2f / segs_full_size: SEGS with the coarse-to-fine resolution (1/4 size for the first quarter
# of the steps, 1/2 for the next) / at full size throughout, whatever the experiment's default. A
# coarse-to-fine warm-up runs at 1/4 size, so give such curves --max-steps or --pace-from
METHODS = {"segs": [], "plain_3dgs": ["+ablation=plain_3dgs"],
           "segs_c2f": ["mapping.num_downscales=2", "mapping.downscale_phase=0.25"],
           "segs_full_size": ["mapping.num_downscales=0"]}  # fmt: skip
MARKS = (15, 30, 60, 120, 300, 600, 1200, 1800, 3600)
TABLE_MINUTES = (1, 2, 5, 10)
PROVISIONAL_STEPS_PER_S = 10.0  # max_steps of the warm-up run only (its schedule is not used)
WARMUP_S = 15.0


class TrainingClock(L.Callback):
    """Wall clock of training (frame feeding + steps) with evaluation at marks, never counted.

    marks: training seconds at which to score; budget: seconds after which training stops
    (also the last mark); score: module -> dict of metrics (called with the clock stopped).
    points: one dict per evaluation {"seconds", "steps", "eval_s", **score(module)}.
    """

    def __init__(self, marks: list[float], budget: float, score: Callable[[L.LightningModule], dict]):
        self.marks = sorted(m for m in marks if m < budget) + [budget]
        self.budget, self.score = budget, score
        self.seconds = 0.0  # training seconds of the finished intervals
        self._since: float | None = None
        self.first_step_s: float | None = None  # training seconds spent before the first step (feeding)
        self.points: list[dict] = []

    def start(self) -> None:
        self._since = time.perf_counter()

    def elapsed(self) -> float:
        return self.seconds + (time.perf_counter() - self._since if self._since is not None else 0.0)

    def stop(self) -> None:
        self.seconds, self._since = self.elapsed(), None

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        if self.first_step_s is None:
            self.first_step_s = self.elapsed()

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        t = self.elapsed()
        last = t >= self.budget or trainer.global_step >= trainer.max_steps
        if last:
            trainer.should_stop = True
        if self.marks and (t >= self.marks[0] or last):
            self.stop()
            while self.marks and self.seconds >= self.marks[0]:
                self.marks.pop(0)
            t0 = time.perf_counter()
            row = self.score(pl_module)
            self.points.append({"seconds": self.seconds, "steps": int(trainer.global_step), "eval_s": time.perf_counter() - t0, **row})
            if last:
                self.marks = []
            self.start()


class RateProbe(L.Callback):
    """Warm-up: stops `seconds` after the first step; rate() = steps/s over the second half,
    feed_s = seconds from the start of fit to the first step (frames fed to the frontend)."""

    def __init__(self, seconds: float):
        self.seconds = seconds
        self.fit_start = time.perf_counter()
        self.feed_s: float | None = None
        self.ticks: list[tuple[float, int]] = []  # (perf_counter, global_step) after each step

    def on_fit_start(self, trainer, pl_module) -> None:
        self.fit_start = time.perf_counter()

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        if self.feed_s is None:
            self.feed_s = time.perf_counter() - self.fit_start

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        self.ticks.append((time.perf_counter(), int(trainer.global_step)))
        if self.ticks[-1][0] - self.ticks[0][0] >= self.seconds:
            trainer.should_stop = True

    def rate(self) -> float:
        mid = (self.ticks[0][0] + self.ticks[-1][0]) / 2 if self.ticks else 0.0
        half = [t for t in self.ticks if t[0] >= mid]
        if len(half) < 2:
            raise RuntimeError(f"warm-up too short: {len(self.ticks)} steps; raise --warmup-s")
        return (half[-1][1] - half[0][1]) / (half[-1][0] - half[0][0])


def warmup(overrides: list[str], seconds: float, budget: float, out: Path) -> RateProbe:
    """A `seconds`-long warm-up of the same run (discarded): its steps/s and feeding seconds."""
    probe = RateProbe(seconds)
    # no loggers, bars, image logging, checkpoints or signal handlers (_harness.QUIET): the clock times mapping only
    cfg, _seq, module, _bridge, trainer = _harness.build_training(overrides, int(PROVISIONAL_STEPS_PER_S * budget) + 1, out, [probe])
    _harness.fit(cfg, module, trainer)
    return probe


def view_scorer(sequence, bridge, out: Path) -> Callable[[L.LightningModule], dict]:
    """module -> {"psnr", "ssim", "test_views", "anchors", "gaussians", "peak_rss_mb"} on the run's
    test views (segs.evaluation.render_test_views; per-view CSV in out/eval_NNN/)."""
    from segs.callbacks.memory import peak_rss_mb
    from segs.evaluation import render_test_views

    calls = [0]

    def score(module) -> dict:
        test, trajectory = bridge.run.test_frames(), bridge.run.trajectory()
        m = render_test_views(module, sequence, trajectory, test, None, 0, out / f"eval_{calls[0]:03d}", progress=False)
        calls[0] += 1
        c = module.counts()
        return {"psnr": m["psnr"], "ssim": m["ssim"], "test_views": m["test_views"], "anchors": c.anchors,
                "gaussians": c.gaussians, "peak_rss_mb": peak_rss_mb()}  # fmt: skip

    return score


def run_scored_at_steps(overrides: list[str], last_step: int, scorer: L.Callback, out: Path) -> None:
    """One run of `overrides` as bench/peers.py runs segs (every frame fed first, QUIET), its
    trainer.max_steps the schedules' floor (mapping.min_schedule_steps) or `last_step` if more, so
    that it trains the schedule the budget-stopped runs train; `scorer` (a callback that stops
    the run at `last_step`) gets `score`: module -> (test PSNR, test SSIM) (view_scorer's)."""
    from segs.config import compose

    floor = int(compose(overrides, output_dir=str(out)).mapping.min_schedule_steps)
    cfg, sequence, module, bridge, trainer = _harness.build_training(overrides, max(floor, last_step), out / "run", [scorer])
    score = view_scorer(sequence, bridge, out)
    scorer.score = lambda m: (lambda r: (float(r["psnr"]), float(r["ssim"])))(score(m))
    _harness.fit(cfg, module, trainer)


def steps_parser(doc: str, datasets: dict) -> argparse.ArgumentParser:
    """The command line of a bench scored at steps of one run (run_scored_at_steps): --dataset (a
    key of `datasets`), --steps, --out (default: steps_record_path's)."""
    ap = argparse.ArgumentParser(description=doc.split("\n")[0])
    ap.add_argument("--dataset", choices=sorted(datasets), default="sample")
    ap.add_argument("--steps", type=int, nargs="+", required=True)
    ap.add_argument("--out", default=None)
    return ap


def steps_record_path(args: argparse.Namespace, name: str) -> Path:
    """--out, or outputs/bench/<name>_<dataset>.json."""
    return Path(args.out) if args.out else ROOT / "outputs" / "bench" / f"{name}_{args.dataset}.json"


def run_curve(overrides: list[str], budget: float, marks: list[float], out: Path, max_steps: int | None = None,
              warmup_s: float = WARMUP_S, wrap_score: Callable | None = None) -> dict:  # fmt: skip
    """One curve: train for `budget` training seconds, scoring the test views at `marks`.

    max_steps None: from a warm-up (module doc). wrap_score: score -> score (tests: slow it down).
    Returns {"max_steps", "warmup_steps_per_s", "feed_s", "fit_wall_s", "train_s", "eval_s",
    "steps", "schedule_done", "points": [...]}."""
    rate = None
    if max_steps is None:
        probe = warmup(overrides, warmup_s, budget, out / "warmup")
        rate = probe.rate()
        max_steps = max(int(rate * max(budget - (probe.feed_s or 0.0), 1.0)), 1)
    clock = TrainingClock(marks, budget, lambda m: {})
    cfg, sequence, module, bridge, trainer = _harness.build_training(overrides, max_steps, out / "run", [clock])
    score = view_scorer(sequence, bridge, out)
    clock.score = wrap_score(score) if wrap_score else score
    t0 = time.perf_counter()
    clock.start()
    _harness.fit(cfg, module, trainer)
    clock.stop()
    fit_wall = time.perf_counter() - t0
    eval_s = sum(p["eval_s"] for p in clock.points)
    return {"max_steps": max_steps, "warmup_steps_per_s": rate, "feed_s": clock.first_step_s,
            "fit_wall_s": fit_wall, "train_s": clock.seconds, "eval_s": eval_s, "steps": int(trainer.global_step),
            "schedule_done": trainer.global_step / max_steps, "points": clock.points}  # fmt: skip


def _uptime() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


def flatten(curves: list[dict]) -> list[dict]:
    """Every curve point with its method and dataset."""
    return [{"method": c["method"], "dataset": c["dataset"], **p} for c in curves for p in c["points"]]


def at_minute(curve: dict, minutes: float) -> dict | None:
    """The first point at or after `minutes` of training; a curve whose schedule ended before
    (steps == max_steps) within its budget gives its final point; None past the budget."""
    point = next((p for p in curve["points"] if p["seconds"] >= minutes * 60 - 1e-9), None)
    if point is None and curve["steps"] >= curve["max_steps"] and minutes * 60 <= curve["budget_s"]:
        return curve["points"][-1]
    return point


def table(curves: list[dict]) -> str:
    """Markdown: PSNR (SSIM) at 1 / 2 / 5 / 10 minutes of training per dataset and method."""
    head = ["dataset", "method"] + [f"{m} min" for m in TABLE_MINUTES] + ["steps (of max_steps)", "anchors / Gaussians", "peak RSS MB"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for c in curves:
        cells = []
        for m in TABLE_MINUTES:
            p = at_minute(c, m)
            done = p is not None and p["seconds"] < m * 60 - 1e-9  # the schedule had ended: its final map
            cells.append("-" if p is None else f"{p['psnr']:.2f} ({p['ssim']:.3f}){' *' if done else ''}")
        last = c["points"][-1]
        lines.append(f"| {c['dataset']} | {c['method']} | " + " | ".join(cells) + f" | {c['steps']} ({c['max_steps']}) | "
                     f"{last['anchors']} / {last['gaussians']} | {last['peak_rss_mb']:.0f} |")  # fmt: skip
    return "\n".join(lines + ["", "PSNR dB (SSIM) at the first evaluation at or after the mark; * the schedule ended earlier "
                               "(max_steps reached): the finished map; - past the budget."])


def chart(curves: list[dict], path: Path) -> None:
    """PSNR vs training seconds (log axis), one panel per dataset, one line per method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    datasets = list(dict.fromkeys(c["dataset"] for c in curves))
    fig, axes = plt.subplots(1, len(datasets), figsize=(4.2 * len(datasets), 3.2), squeeze=False)
    for ax, name in zip(axes[0], datasets):
        for c in (c for c in curves if c["dataset"] == name):
            ax.plot([p["seconds"] for p in c["points"]], [p["psnr"] for p in c["points"]], marker="o", ms=3, label=c["method"])
        seconds: list[int] = []  # tick labels: the points' seconds, at least 25 % apart
        for t in sorted({round(p["seconds"]) for c in curves if c["dataset"] == name for p in c["points"]}):
            if not seconds or t >= 1.25 * seconds[-1]:
                seconds.append(t)
        ax.set_xscale("log")
        ax.xaxis.set_major_locator(matplotlib.ticker.FixedLocator(seconds))
        ax.xaxis.set_major_formatter(matplotlib.ticker.FixedFormatter([str(s) for s in seconds]))
        ax.xaxis.set_minor_locator(matplotlib.ticker.NullLocator())
        ax.tick_params(labelsize=7)
        views = next(c["points"][-1]["test_views"] for c in curves if c["dataset"] == name)
        ax.set_title(f"{name} ({views} test views)", fontsize=10)
        ax.set_xlabel("training seconds (wall clock, evaluation excluded)", fontsize=8)
        ax.set_ylabel("test-view PSNR (dB)", fontsize=8)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def write_outputs(record: dict, json_path: Path, png_path: Path) -> None:
    """The JSON (record + flat points) and the chart."""
    _harness.write_json(json_path, {**record, "points": flatten(record["curves"])})
    chart(record["curves"], png_path)


def paced_steps(path: Path | None, dataset: str, method: str, budget: float) -> int | None:
    """The steps the same curve (dataset, method, budget) reached in the output JSON at path."""
    if path is None:
        return None
    curves = json.loads(path.read_text())["curves"]
    return next((c["steps"] for c in curves if (c["dataset"], c["method"], c["budget_s"]) == (dataset, method, budget)), None)


def _one(args) -> None:
    """--curve DATASET METHOD: one curve in this process, written to --part."""
    dataset, method = args.curve
    budget = args.sample_budget if dataset == "sample" and args.sample_budget else args.budget
    out = Path(tempfile.mkdtemp(prefix=f"ttq_{dataset}_{method}_", dir=args.work))
    res = run_curve(DATASETS[dataset] + METHODS[method] + [f"seed={args.seed}"] + args.extra, budget, args.marks, out,
                    args.max_steps or paced_steps(args.pace_from, dataset, method, budget), args.warmup_s)  # fmt: skip
    _harness.write_json(args.part, {"dataset": dataset, "method": method, "budget_s": budget, **res})


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--budget", type=float, default=600.0, help="training seconds per curve")
    p.add_argument("--sample-budget", type=float, default=300.0, help="training seconds per sample curve (0: --budget)")
    p.add_argument("--marks", type=float, nargs="+", default=list(MARKS), help="training seconds to score at (below the budget)")
    p.add_argument("--datasets", nargs="+", default=list(DATASETS), choices=list(DATASETS))
    p.add_argument("--methods", nargs="+", default=["segs", "plain_3dgs"], choices=list(METHODS))
    p.add_argument("--max-steps", type=int, default=None, help="trainer.max_steps of every curve (default: from a warm-up)")
    p.add_argument("--warmup-s", type=float, default=WARMUP_S, help="seconds of warm-up training to measure steps/s")
    p.add_argument("--pace-from", type=Path, default=None,
                   help="an earlier output JSON: max_steps of each curve = the steps that curve reached there (same budget)")
    p.add_argument("--report", type=Path, default=None, help="only print the table and redraw the chart of this output JSON")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--extra", nargs="*", default=[], help="more overrides for every run")
    p.add_argument("--work", default=str(_harness.OUTPUTS / "time_to_quality"), help="per-curve run folders")
    p.add_argument("--out", default=str(_harness.OUTPUTS / "time_to_quality.json"))
    p.add_argument("--chart", default=str(ROOT / "docs" / "performance" / "time_to_quality.png"))
    p.add_argument("--curve", nargs=2, metavar=("DATASET", "METHOD"), help=argparse.SUPPRESS)
    p.add_argument("--part", help=argparse.SUPPRESS)
    args = p.parse_args()
    Path(args.work).mkdir(parents=True, exist_ok=True)
    if args.curve:
        return _one(args)
    if args.report:
        record = json.loads(args.report.read_text())
        chart(record["curves"], Path(args.chart))
        print(f"{record['machine']['cpu']}; before: {record['machine']['uptime']}; after: {record.get('uptime_after')}")
        return print(table(record["curves"]))
    if "7scenes" in args.datasets and not (SEVEN_SCENES / "seq").is_dir():
        print(f"time_to_quality: skipping 7scenes: the shared frames are not at {SEVEN_SCENES}", file=sys.stderr)
        args.datasets.remove("7scenes")
    record = {**_harness.record(), "command": " ".join(["python bench/time_to_quality.py"] + sys.argv[1:]), "curves": []}
    record["machine"]["uptime"] = _uptime()
    for dataset in args.datasets:
        for method in args.methods:
            part = Path(args.work) / f"{dataset}_{method}.json"
            cmd = [sys.executable, __file__, "--curve", dataset, method, "--part", str(part)] + [a for a in sys.argv[1:]]
            print(f"time_to_quality: {dataset} / {method}", flush=True)
            subprocess.run(cmd, check=True, cwd=ROOT)
            record["curves"].append(json.loads(part.read_text()))
            record["uptime_after"] = _uptime()
            write_outputs(record, Path(args.out), Path(args.chart))  # after every curve: an interrupted run keeps its curves
    print(f"{record['machine']['cpu']}, {record['machine']['torch_threads']} threads; before: {record['machine']['uptime']}; "
          f"after: {record.get('uptime_after')}")
    print(table(record["curves"]))


if __name__ == "__main__":
    main()
