"""Benchmark segs.raster backends: forward, backward and forward+backward milliseconds.

    python bench/raster.py                      # cpu and torch (and cuda if available)
    python bench/raster.py --runs 20 --backends cpu --build-times

Scenes come from segs.raster.scenes.random_scene (seed 0): 320x240 with 20k Gaussians and
640x480 with 100k. Each backend does --warmup untimed iterations, then --runs timed ones,
alternating between backends (a load change on a shared machine hits all of them); the table
shows medians. The loss uses image, depth and alpha, so backward covers all three.
"Mpair/s" is the nominal work, (tile, Gaussian) pairs of the 3-sigma tile lists x 256 pixels,
divided by the forward+backward time: the same numerator for every backend.
Figures are also written as JSON (default outputs/bench/raster.json).
"""
from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time

import _harness

_harness.apply_process_settings()  # before torch loads

import torch

from segs.raster import _cpu_backend, _torch_backend, available_backends, rasterize
from segs.raster._projection import project
from segs.raster.scenes import random_scene


def scene_stats(scene, backend: str) -> dict:
    """Visible Gaussians, nominal pairs ((tile, Gaussian) pairs of the 3-sigma tile lists x 256,
    the work 3D-GS schedules) and how much of the image is covered."""
    with torch.no_grad():
        p = project(scene.means, scene.quats, scene.scales, scene.viewmat, scene.K,
                    scene.width, scene.height, 0.01, 100.0)
        ids, _ = _torch_backend.bin_gaussians(p.means2d, p.depths, p.radii, scene.width, scene.height)
        dev = "cuda" if backend == "cuda" else "cpu"
        r = rasterize(*[t.to(dev) for t in scene.params()], scene.viewmat.to(dev), scene.K.to(dev),
                      scene.width, scene.height, backend=backend)
    return {"visible": int((p.radii > 0).sum()), "nominal_pairs": int(ids.numel()) * 256,
            "alpha_mean": float(r.alpha.mean()), "alpha_gt_0.99": float((r.alpha > 0.99).float().mean())}


def _sync(device: str) -> None:
    if device == "cuda":
        torch.cuda.synchronize()


class Timer:
    """One backend on one scene: timed forward and backward iterations."""

    def __init__(self, scene, backend: str):
        self.backend, self.device = backend, ("cuda" if backend == "cuda" else "cpu")
        self.params = [p.detach().to(self.device).requires_grad_(True) for p in scene.params()]
        self.cam = (scene.viewmat.to(self.device), scene.K.to(self.device))
        self.size = (scene.width, scene.height)
        w, h = self.size
        self.weights = torch.rand(h, w, 3, generator=torch.Generator().manual_seed(1)).to(self.device)
        self.fwd, self.bwd = [], []

    def step(self, record: bool) -> None:
        for p in self.params:
            p.grad = None
        _sync(self.device)
        t0 = time.perf_counter()
        r = rasterize(*self.params, *self.cam, *self.size, backend=self.backend)
        _sync(self.device)
        t1 = time.perf_counter()
        loss = (r.image * self.weights).sum() + 0.1 * r.depth.sum() + r.alpha.sum()
        loss.backward()
        _sync(self.device)
        t2 = time.perf_counter()
        if record:
            self.fwd.append(t1 - t0)
            self.bwd.append(t2 - t1)

    def summary(self) -> dict:
        med = lambda xs: 1000.0 * statistics.median(xs)  # noqa: E731
        out = {"forward_ms": med(self.fwd), "backward_ms": med(self.bwd),
               "fwd_bwd_ms": med([a + b for a, b in zip(self.fwd, self.bwd)]), "runs": len(self.fwd)}
        if self.backend == "cpu":
            out["cpu_work"] = dict(_cpu_backend.LAST_STATS)
        return out


def time_backends(scene, backends: list[str], runs: int, warmup: int) -> dict:
    """Medians per backend; iterations alternate between backends so load changes hit all."""
    timers = {b: Timer(scene, b) for b in backends}
    start = time.perf_counter()
    for i in range(warmup + runs):
        for t in timers.values():
            t.step(record=i >= warmup)
        print(f"#   iteration {i + 1}/{warmup + runs} ({time.perf_counter() - start:.0f} s)",
              file=sys.stderr, flush=True)
    return {b: t.summary() for b, t in timers.items()}


def build_times() -> dict:
    """Cold build into an empty cache, then the load of the cached build (fresh processes, after
    ``import torch``, which alone takes about a second)."""
    code = ("import time, torch; t = time.perf_counter(); from segs.raster._build import "
            "load_extension; load_extension(); print(time.perf_counter() - t)")
    with tempfile.TemporaryDirectory() as tmp:
        env = {**os.environ, "SEGS_RASTER_CACHE_DIR": tmp}
        run = lambda: float(subprocess.run([sys.executable, "-c", code], env=env, check=True,  # noqa: E731
                                           capture_output=True, text=True).stdout.split()[-1])
        return {"cold_build_s": run(), "cached_load_s": run()}


def print_table(results: list[dict]) -> None:
    head = f"{'backend':8} {'size':>9} {'N':>7} {'fwd ms':>9} {'bwd ms':>9} {'f+b ms':>9} {'x torch':>8} {'Mpair/s':>8}"
    print(head)
    print("-" * len(head))
    for r in results:
        speed = f"{r['speedup_vs_torch']:.1f}" if r.get("speedup_vs_torch") else "-"
        print(f"{r['backend']:8} {r['size']:>9} {r['n']:>7} {r['forward_ms']:9.1f} "
              f"{r['backward_ms']:9.1f} {r['fwd_bwd_ms']:9.1f} {speed:>8} {r['mpairs_per_s']:8.1f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=10)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--backends", default=",".join(b for b in ("cuda", "cpu", "torch")
                                                   if b in available_backends()))
    ap.add_argument("--sizes", default="320x240:20000,640x480:100000")
    ap.add_argument("--threads", type=int, default=None, help="torch.set_num_threads")
    ap.add_argument("--build-times", action="store_true", help="also time a cold build")
    ap.add_argument("--out", default=str(_harness.OUTPUTS / "raster.json"))
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    info = {**_harness.record(), "torch": torch.__version__,
            "cuda": torch.cuda.get_device_name() if torch.cuda.is_available() else None, "results": []}
    backends = args.backends.split(",")
    for spec in args.sizes.split(","):
        size, n = spec.split(":")
        width, height = map(int, size.split("x"))
        scene = random_scene(int(n), width, height, seed=0)
        stats = scene_stats(scene, backends[0])
        pairs = stats["nominal_pairs"]
        info.setdefault("scenes", {})[spec] = stats
        print(f"# {size} N={n}: {', '.join(backends)} ...", file=sys.stderr, flush=True)
        rows = {}
        for b, summary in time_backends(scene, backends, args.runs, args.warmup).items():
            rows[b] = {"backend": b, "size": size, "n": int(n), **summary}
            rows[b]["mpairs_per_s"] = pairs / rows[b]["fwd_bwd_ms"] / 1e3
        for row in rows.values():
            if "torch" in rows:
                row["speedup_vs_torch"] = rows["torch"]["fwd_bwd_ms"] / row["fwd_bwd_ms"]
            info["results"].append(row)
    if args.build_times:
        info["build"] = build_times()
    info["machine"]["load_avg_end"] = _harness.load_average()
    m = info["machine"]
    print(f"{m['cpu']}, {m['cores']} CPUs, torch {info['torch']} with {m['torch_threads']} "
          f"threads, {info['time']}, load {m['load_avg'][0]:.1f} -> {m['load_avg_end'][0]:.1f}")
    print_table(info["results"])
    for spec, st in info["scenes"].items():
        print(f"scene {spec}: {st['visible']} visible, {st['nominal_pairs'] / 1e6:.1f} M nominal "
              f"pairs, mean alpha {st['alpha_mean']:.3f}, alpha > 0.99 on {st['alpha_gt_0.99']:.1%}")
    if "build" in info:
        print(f"cold build {info['build']['cold_build_s']:.1f} s, "
              f"cached load {info['build']['cached_load_s']:.2f} s")
    print(f"wrote {_harness.write_json(args.out, info)}")


if __name__ == "__main__":
    main()
