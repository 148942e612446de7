"""FPR's multi-scale loss (segs.modules.fpr.pyramid_loss), eager (as training runs it on every
device) against its torch.compile form: forward + backward per call, the values compared.

    python bench/fpr.py --device cuda                 # 640x480, the paper's protocol size
    python bench/fpr.py --device cpu --size 320 240

Per form: --warmup untimed calls (the compilation), then --repeats timings of --calls calls each
(ending in a device sync); the table gives the medians in ms per call, the forms alternated.
Writes outputs/bench/fpr.json.
"""
from __future__ import annotations

import argparse
import statistics
import time

import _harness

_harness.apply_process_settings()  # before torch loads

import torch

from segs.modules.fpr import pyramid_loss, pyramid_weights


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default="cuda")
    p.add_argument("--size", type=int, nargs=2, default=(640, 480), metavar=("W", "H"))
    p.add_argument("--scales", type=int, default=3)
    p.add_argument("--calls", type=int, default=50)
    p.add_argument("--repeats", type=int, default=7)
    p.add_argument("--warmup", type=int, default=5)
    p.add_argument("--out", default=str(_harness.OUTPUTS / "fpr.json"))
    args = p.parse_args()
    dev = torch.device(args.device)
    w, h = args.size
    torch.manual_seed(0)
    gt = torch.rand(h, w, 3, device=dev)
    render = (gt + 0.1 * torch.randn_like(gt)).clamp(0, 1).requires_grad_(True)
    weights = pyramid_weights(h, w, args.scales, "high", 0.4, 0.1, str(dev))
    forms = {"eager": pyramid_loss, "compiled": torch.compile(pyramid_loss)}
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)

    def calls(fn) -> float:
        t = time.perf_counter()
        for _ in range(args.calls):
            (g,) = torch.autograd.grad(fn(render, gt, weights), render)
        sync()
        return (time.perf_counter() - t) * 1000.0 / args.calls

    values = {}
    for name, fn in forms.items():
        loss = fn(render, gt, weights)
        values[name] = (float(loss), torch.autograd.grad(loss, render)[0])
        for _ in range(args.warmup):
            calls(fn)
    times: dict[str, list[float]] = {n: [] for n in forms}
    for _ in range(args.repeats):
        for name, fn in forms.items():
            times[name].append(calls(fn))
    med = {n: statistics.median(t) for n, t in times.items()}
    grad_diff = float((values["compiled"][1] - values["eager"][1]).abs().max())
    print(f"FPR, {args.scales} scales, {w}x{h} on {dev}: eager {med['eager']:.3f} ms per forward+backward, compiled "
          f"{med['compiled']:.3f} ms ({med['compiled'] / med['eager']:.2f}x); loss {values['eager'][0]:.6f} / "
          f"{values['compiled'][0]:.6f}, largest gradient difference {grad_diff:.2e}")  # fmt: skip
    _harness.write_json(args.out, {**_harness.record(), "args": vars(args), "ms_per_call": med, "runs": times,
                                   "loss": {n: v[0] for n, v in values.items()}, "max_grad_diff": grad_diff})  # fmt: skip


if __name__ == "__main__":
    main()
