"""Mapping iteration time on the bundled real TUM sample (or another experiment), per model, with a breakdown.

Builds the run as `python -m segs.train` builds it (segs.train.build: known poses, 320x240 on the
sample, no loggers or checkpoints) and feeds every frame before the first step, so the map holds
every keyframe; a Lightning trainer then runs the module's own `training_step`: `--warmup`
untimed steps of a `--schedule`-step run (densification on, so the Gaussian count is what that
point of a real run has), then `--iters` timed ones. Per step: decode (model.decode), rasterize
(forward), loss (model.loss), backward (manual_backward), step+stats (the rest of training_step:
view sampling, densification statistics, learning rates, Adam step, densification) and total
(the step's own clock, GaussianMapperModule.iteration_ms: what segs.train reports as
train/iteration_ms). The warm-up runs at full size and the timed steps at 1/--downscale, whatever
the experiment's coarse-to-fine schedule. Prints one table (medians) and writes
outputs/bench/train_step.json.

    python bench/train_step.py --schedule 3000 --warmup 1500 --iters 30
    python bench/train_step.py --experiment seven_scenes_rgbd --extra data.frames=[100,250]   # 640x480
    python bench/train_step.py --downscale 4   # the timed iterations at 1/4 size (coarse-to-fine's first phase)
    python bench/train_step.py --models segs --variant model.k=5   # the defaults and a variant, timed alternately
    python bench/train_step.py --backend cuda --device cuda --profile   # wall vs device time per step (GPU)
    python bench/train_step.py --backend cuda --device cuda --profile --extra mapping.compile=false   # the same, eager

With --profile the phases are not synchronised: the timed steps run as in segs.train under
torch.profiler, and the table gives wall time per step against the device's kernel time per step;
their difference is the time the device waits for the host (Python, launches, syncs).
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import _harness

_harness.apply_process_settings()  # before torch loads

import lightning as L
import torch

from segs.modules.gaussian_mapper import GaussianMapperModule
from segs.modules.resolution import coarse_camera

PHASES = ("decode", "raster_fwd", "loss", "backward")


class StepTimes(L.Callback):
    """Times the phases of the module's training_step by wrapping what it calls on this module
    (render = model.decode + the rasterizer, model.decode, model.loss, manual_backward: the step
    itself runs unchanged), one row per step after `warmup` steps; stops the trainer after `iters`
    rows. rows: {phase: seconds, "step+stats", "total", "gaussians"}."""

    def __init__(self, module: GaussianMapperModule, warmup: int, iters: int, factor: int = 1):
        self.warmup, self.iters, self.steps, self.rows = warmup, iters, 0, []
        self._now: dict[str, float] = {}
        self._gaussians = 0
        dev = str(module.device)
        self._sync = (lambda: torch.cuda.synchronize()) if dev.startswith("cuda") else (lambda: None)
        module.render = self._timed("render", module.render)
        module.model.decode = self._timed("decode", module.model.decode)
        module.model.loss = self._timed("loss", module.model.loss)
        module.manual_backward = self._timed("backward", module.manual_backward)
        # the warm-up at full size, the timed steps at 1/factor size, whatever the configured
        # coarse-to-fine schedule (mapping.num_downscales) would give at those steps
        module.resolution_factor = lambda step: factor if self.steps >= warmup else 1

    def _timed(self, name: str, fn):
        def timed(*args, **kwargs):
            self._sync()
            t0 = time.perf_counter()
            out = fn(*args, **kwargs)
            self._sync()
            self._now[name] = self._now.get(name, 0.0) + time.perf_counter() - t0
            if name == "decode":
                self._gaussians = len(out)
            return out

        return timed

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        self._now = {}

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        self.steps += 1
        if self.steps > self.warmup:
            total = pl_module.iteration_ms[-1] / 1e3
            now = {k: self._now.get(k, 0.0) for k in ("render", *PHASES)}
            now["raster_fwd"] = now.pop("render") - now["decode"]
            row = {k: now[k] for k in PHASES}
            self.rows.append({**row, "step+stats": total - sum(row.values()), "total": total, "gaussians": float(self._gaussians)})
        if len(self.rows) >= self.iters:
            trainer.should_stop = True


class DeviceBusy(L.Callback):
    """Wall seconds of `iters` steps after `warmup` (first batch start to last batch end, the loop
    between them included) and the device kernels' total time over them (torch.profiler); stops
    the trainer after them. Result in `row`: wall / device ms per step, device share, top host ops."""

    def __init__(self, warmup: int, iters: int, cuda: bool):
        self.warmup, self.iters, self.cuda, self.steps, self.row = warmup, iters, cuda, 0, {}
        self._prof, self._t0 = None, 0.0

    def _sync(self) -> None:
        if self.cuda:
            torch.cuda.synchronize()

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        if self.steps == self.warmup:
            from torch.profiler import ProfilerActivity, profile
            acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if self.cuda else [])
            self._sync()
            self._prof = profile(activities=acts)
            self._prof.__enter__()
            self._t0 = time.perf_counter()

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        self.steps += 1
        if self.steps < self.warmup + self.iters:
            return
        self._sync()
        wall = (time.perf_counter() - self._t0) / self.iters
        self._prof.__exit__(None, None, None)
        ev = self._prof.key_averages()
        device = sum(e.self_device_time_total for e in ev) / 1e6 / self.iters if self.cuda else None
        top = sorted(ev, key=lambda e: e.self_cpu_time_total, reverse=True)[:12]
        self.row = {"wall": wall, "device": device, "device_share": None if device is None else device / wall,
                    "kernels_per_step": sum(e.count for e in ev if e.device_type.name == "CUDA") / self.iters if self.cuda else None,
                    "top_host_ops_ms": {e.key: e.self_cpu_time_total / 1e3 / self.iters for e in top}}
        trainer.should_stop = True
        self._prof = None

    def on_train_end(self, trainer, pl_module) -> None:
        if self._prof is not None:  # the schedule ended inside the profiled steps: no row
            self._prof.__exit__(None, None, None)
            self._prof = None


def _overrides(experiment: str, backend: str, device: str, extra=()) -> list[str]:
    """The run's overrides: the experiment with known poses, on this backend and device, + extra."""
    return [f"+experiment={experiment}", "slam=known_poses", f"raster.backend={backend}",
            f"trainer.accelerator={'gpu' if device.startswith('cuda') else 'cpu'}", *extra]


def profiled(schedule: int, warmup: int, iters: int, backend: str, device: str, experiment: str, extra=(), factor: int = 1) -> dict:
    """DeviceBusy's row for SEGS (+ extra) after `warmup` steps of a `schedule`-step run."""
    overrides = _overrides(experiment, backend, device, extra)
    with tempfile.TemporaryDirectory(prefix="train_step_profile_") as out:
        cfg, _seq, module, _bridge, trainer = _harness.build_training(overrides, schedule, Path(out), [])
        module.resolution_factor = lambda step: factor
        busy = DeviceBusy(warmup, iters, device.startswith("cuda"))
        trainer.callbacks.append(busy)
        _harness.fit(cfg, module, trainer)
    if not busy.row:
        raise SystemExit(f"bench/train_step.py: {busy.steps} steps ran, {warmup + iters} needed (raise --schedule)")
    return {**busy.row, "anchors": int(module.model.counts()["anchors"])}


def bench(model: str, schedule: int, warmup: int, iters: int, backend: str, device: str = "cpu",
          experiment: str = "sample", extra=(), factor: int = 1) -> dict:
    """Medians of the timed steps of one model (module doc), with its anchors and image size."""
    overrides = _overrides(experiment, backend, device, (["+ablation=plain_3dgs"] if model == "plain_3dgs" else []) + list(extra))
    with tempfile.TemporaryDirectory(prefix=f"train_step_{model}_") as out:
        cfg, _seq, module, _bridge, trainer = _harness.build_training(overrides, schedule, Path(out), [])
        times = StepTimes(module, warmup, iters, factor)
        trainer.callbacks.append(times)
        _harness.fit(cfg, module, trainer)
    if len(times.rows) < iters:
        raise SystemExit(f"bench/train_step.py: {model}: {len(times.rows)} timed steps of {iters} "
                         f"(the schedule has {schedule}; raise --schedule)")
    med = _harness.medians(times.rows)
    med["anchors"] = int(module.model.counts()["anchors"])
    cam = coarse_camera(module.views.sample().camera, factor)
    med["size"] = f"{cam.width}x{cam.height}"
    return med


def interleaved(schedule: int, warmup: int, iters: int, backend: str, experiment: str, extra, variant, factor: int = 1,
                repeats: int = 1) -> dict:
    """Seconds per iteration of the SEGS defaults (+ extra) and of the same + variant: `repeats`
    runs of each, alternated (A B A B ...), each warmed up on its own `schedule` for `warmup`
    steps and timed as `bench` times it; medians over the runs' medians, and the ratio B / A."""
    runs: dict[str, list[dict]] = {"defaults": [], "variant": []}
    for _ in range(repeats):
        for name, overrides in (("defaults", list(extra)), ("variant", list(extra) + list(variant))):
            runs[name].append(bench("segs", schedule, warmup, iters, backend, "cpu", experiment, overrides, factor))
    med = {name: _harness.medians(rows) for name, rows in runs.items()}
    out = {name: {"total": m["total"], "gaussians": m["gaussians"], "anchors": runs[name][-1]["anchors"]} for name, m in med.items()}
    out["ratio"] = out["variant"]["total"] / out["defaults"]["total"]
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--schedule", type=int, default=3000, help="trainer.max_steps of the run being imitated")
    p.add_argument("--warmup", type=int, default=1500)
    p.add_argument("--iters", type=int, default=30)
    p.add_argument("--backend", default="cpu")
    p.add_argument("--models", nargs="+", default=["segs", "plain_3dgs"])
    p.add_argument("--device", default="cpu", help="torch device of the model (cuda with --backend cuda)")
    p.add_argument("--experiment", default="sample", help="+experiment=NAME (with slam=known_poses)")
    p.add_argument("--extra", nargs="*", default=[], help="more config overrides, e.g. data.frames=[100,250]")
    p.add_argument("--downscale", type=int, default=1, help="time the iterations at 1/N of the image size (warm-up at full size)")
    p.add_argument("--variant", nargs="+", default=None, help="overrides of a SEGS variant, timed in runs alternated with the defaults")
    p.add_argument("--repeats", type=int, default=1, help="runs of each with --variant")
    p.add_argument("--profile", action="store_true", help="wall vs device kernel time per step (SEGS; no phase syncs)")
    p.add_argument("--out", default=str(_harness.OUTPUTS / "train_step.json"))
    args = p.parse_args()
    if args.profile:
        row = profiled(args.schedule, args.warmup, args.iters, args.backend, args.device, args.experiment, args.extra, args.downscale)
        dev = "n/a (no CUDA)" if row["device"] is None else f"{1000 * row['device']:.1f} ms ({100 * row['device_share']:.0f} % of wall, " \
            f"{row['kernels_per_step']:.0f} kernels)"
        print(f"SEGS, {row['anchors']} anchors, {args.iters} steps after {args.warmup} of {args.schedule}: "
              f"wall {1000 * row['wall']:.1f} ms per step, device kernels {dev}")
        for k, v in row["top_host_ops_ms"].items():
            print(f"  host {v:7.2f} ms/step  {k}")
        _harness.write_json(args.out, {**_harness.record(), "args": vars(args), "profile": row})
        return
    if args.variant:
        res = interleaved(args.schedule, args.warmup, args.iters, args.backend, args.experiment, args.extra, args.variant,
                          args.downscale, args.repeats)
        print(f"medians of {args.iters} iterations in {args.repeats} alternated runs of each after {args.warmup} of a "
              f"{args.schedule}-step schedule: defaults "
              f"{1000 * res['defaults']['total']:.1f} ms ({res['defaults']['anchors']} anchors, {res['defaults']['gaussians']:.0f} drawn), "
              f"{' '.join(args.variant)} {1000 * res['variant']['total']:.1f} ms ({res['variant']['anchors']} anchors, "
              f"{res['variant']['gaussians']:.0f} drawn): ratio {res['ratio']:.3f}")  # fmt: skip
        return
    results = {m: bench(m, args.schedule, args.warmup, args.iters, args.backend, args.device, args.experiment, args.extra, args.downscale)
               for m in args.models}
    record = _harness.record()
    gpu = torch.cuda.get_device_name() if args.device.startswith("cuda") else None
    size = next(iter(results.values()))["size"]
    print(f"{gpu or record['machine']['cpu']}, {torch.get_num_threads()} threads, backend {args.backend}, {size}, "
          f"medians of {args.iters} iterations after {args.warmup} of a {args.schedule}-step schedule")
    keys = ["decode", "raster_fwd", "loss", "backward", "step+stats", "total"]
    print(f"| model | Gaussians drawn | anchors | {' | '.join(k + ' ms' for k in keys)} | it/s |")
    print("|---|---|---|" + "---|" * (len(keys) + 1))
    for m, r in results.items():
        cells = " | ".join(f"{1000 * r[k]:.1f}" for k in keys)
        print(f"| {m} | {r['gaussians']:.0f} | {r['anchors']} | {cells} | {1 / r['total']:.2f} |")
    _harness.write_json(args.out, {**record, "gpu": gpu, "args": vars(args), "results": results})


if __name__ == "__main__":
    main()
