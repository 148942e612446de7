"""Mapping iteration time on the bundled real TUM sample (or another experiment), per model, with a breakdown.

Builds the map of every sample keyframe from known poses (320x240), warms each model up with
`--warmup` training iterations of a `--schedule`-step run (densification on, so the Gaussian
count is what that point of a real run has), then
times `--iters` iterations: decode, rasterize (forward), loss, backward (raster + decoders +
loss), optimizer step. Prints one table (medians) and writes outputs/bench/train_step.json.

    python bench/train_step.py --schedule 3000 --warmup 1500 --iters 30
    python bench/train_step.py --experiment seven_scenes_rgbd --extra data.frames=[100,250]   # 640x480
    python bench/train_step.py --downscale 4   # the timed iterations at 1/4 size (coarse-to-fine's first phase)
    python bench/train_step.py --models segs --variant model.k=5   # the defaults and a variant, timed alternately
"""
from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np
import torch

from segs.callbacks.bridge import SlamBridge
from segs.config import compose, instantiate, make_sequence
from segs.modules.config import build_model, mapping_config, raster_config
from segs.modules.gaussian_mapper import GaussianMapperModule
from segs.modules.optim import make_adam, set_learning_rates
from segs.modules.resolution import coarse_camera, coarse_image
from segs.modules.scene_model import View
from segs.raster import rasterize

ROOT = Path(__file__).resolve().parents[1]


def build(model: str, steps: int, backend: str, device: str = "cpu", experiment: str = "sample", extra=()):
    cfg = compose([f"+experiment={experiment}", "slam=known_poses", f"trainer.max_steps={steps}", f"raster.backend={backend}"]
                  + (["+ablation=plain_3dgs"] if model == "plain_3dgs" else []) + list(extra), output_dir="/tmp/segs_bench")  # fmt: skip
    seq = make_sequence(cfg.data)
    frontend = instantiate(cfg.slam)(camera=seq.camera, sensor=seq.sensor)
    module = GaussianMapperModule(build_model(cfg.model), mapping_config(cfg.mapping), raster_config(cfg.raster), seed=cfg.seed)
    module.to(device)
    bridge = SlamBridge(seq, frontend, progress=False)
    for _ in range(len(seq)):
        bridge._feed_one()
        bridge._push(frontend.poll(), module)
    return module


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def iteration(module: GaussianMapperModule, opt, step: int, timed: bool, factor: int = 1) -> dict:
    t = {}
    dev = str(module.device)
    clock = lambda: (_sync(dev), time.perf_counter())[1]  # noqa: E731
    kf = module.views.sample()
    view = View(kf.w2c.to(dev), coarse_camera(kf.camera, factor), kf.kf_id)
    gt = coarse_image(kf.rgb().to(dev), factor)
    t0 = clock()
    dec = module.model.decode(view, step)
    t1 = clock()
    out = rasterize(dec.means, dec.quats, dec.scales, dec.opacities, dec.colors, view.w2c, view.K.to(dev), view.camera.width,
                    view.camera.height, background=torch.zeros(3, device=dev), backend=module.raster.backend)  # fmt: skip
    t2 = clock()
    terms = module.model.loss(out, gt, dec, step)
    t3 = clock()
    terms["total"].backward()
    t4 = clock()
    module.model.after_backward(dec, out, step)
    set_learning_rates(opt, module.model.lr_schedules(), step)
    opt.step()
    opt.zero_grad(set_to_none=True)
    module.model.maintain(step + 1, opt)
    t5 = clock()
    if timed:
        t = {"decode": t1 - t0, "raster_fwd": t2 - t1, "loss": t3 - t2, "backward": t4 - t3, "step+stats": t5 - t4, "total": t5 - t0,
             "gaussians": len(dec)}  # fmt: skip
    return t


def bench(model: str, schedule: int, warmup: int, iters: int, backend: str, device: str = "cpu",
          experiment: str = "sample", extra=(), factor: int = 1) -> dict:
    torch.manual_seed(0)
    module = build(model, schedule, backend, device, experiment, extra)
    opt = make_adam(module.model.param_groups())
    for s in range(warmup):
        iteration(module, opt, s, False)
    rows = [iteration(module, opt, warmup + i, True, factor) for i in range(iters)]
    med = {k: float(np.median([r[k] for r in rows])) for k in rows[0]}
    med["anchors"] = int(module.model.counts()["anchors"])
    view = module.views.sample()
    cam = coarse_camera(view.camera, factor)
    med["size"] = f"{cam.width}x{cam.height}"
    return med


def interleaved(schedule: int, warmup: int, iters: int, backend: str, experiment: str, extra, variant, factor: int = 1) -> dict:
    """Seconds per iteration of the SEGS defaults (+ extra) and of the same + variant, each warmed
    up on its own `schedule` for `warmup` steps, then timed alternately (A B A B ...): medians,
    and the ratio B / A of the medians."""
    models = {}
    for name, overrides in (("defaults", list(extra)), ("variant", list(extra) + list(variant))):
        torch.manual_seed(0)
        module = build("segs", schedule, backend, "cpu", experiment, overrides)
        opt = make_adam(module.model.param_groups())
        for s in range(warmup):
            iteration(module, opt, s, False)
        models[name] = (module, opt, [])
    for i in range(iters):
        for module, opt, rows in models.values():
            rows.append(iteration(module, opt, warmup + i, True, factor))
    out = {name: {"total": float(np.median([r["total"] for r in rows])), "gaussians": float(np.median([r["gaussians"] for r in rows])),
                  "anchors": int(module.model.counts()["anchors"])} for name, (module, _, rows) in models.items()}  # fmt: skip
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
    p.add_argument("--variant", nargs="+", default=None, help="overrides of a SEGS variant timed alternately with the defaults")
    p.add_argument("--out", default=str(ROOT / "outputs" / "bench" / "train_step.json"))
    args = p.parse_args()
    if args.variant:
        res = interleaved(args.schedule, args.warmup, args.iters, args.backend, args.experiment, args.extra, args.variant, args.downscale)
        print(f"medians of {args.iters} alternated iterations after {args.warmup} of a {args.schedule}-step schedule: defaults "
              f"{1000 * res['defaults']['total']:.1f} ms ({res['defaults']['anchors']} anchors, {res['defaults']['gaussians']:.0f} drawn), "
              f"{' '.join(args.variant)} {1000 * res['variant']['total']:.1f} ms ({res['variant']['anchors']} anchors, "
              f"{res['variant']['gaussians']:.0f} drawn): ratio {res['ratio']:.3f}")  # fmt: skip
        return
    results = {m: bench(m, args.schedule, args.warmup, args.iters, args.backend, args.device, args.experiment, args.extra, args.downscale)
               for m in args.models}
    cpu = next((line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name")), platform.processor())
    gpu = torch.cuda.get_device_name() if args.device.startswith("cuda") else None
    size = next(iter(results.values()))["size"]
    print(f"{gpu or cpu}, {torch.get_num_threads()} threads, backend {args.backend}, {size}, medians of {args.iters} iterations "
          f"after {args.warmup} of a {args.schedule}-step schedule")
    keys = ["decode", "raster_fwd", "loss", "backward", "step+stats", "total"]
    print(f"| model | Gaussians drawn | anchors | {' | '.join(k + ' ms' for k in keys)} | it/s |")
    print("|---|---|---|" + "---|" * (len(keys) + 1))
    for m, r in results.items():
        cells = " | ".join(f"{1000 * r[k]:.1f}" for k in keys)
        print(f"| {m} | {r['gaussians']:.0f} | {r['anchors']} | {cells} | {1 / r['total']:.2f} |")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    record = {"cpu": cpu, "gpu": gpu, "threads": torch.get_num_threads(), "args": vars(args), "results": results}
    out.write_text(json.dumps(record, indent=2))


if __name__ == "__main__":
    main()
