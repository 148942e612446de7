"""The cost of a written training step's logging (GaussianMapperModule._log_step) in a
`segs.train` run on the sample with its tensorboard logger: milliseconds per written step.

    python bench/log_step.py                      # 300 steps, written every 10 (the default cadence)
    python bench/log_step.py --steps 600 --every 5

The step's own time (train/iteration_ms) leaves the logging out; this times it alone, wrapping
the method, over every written step of the run. Prints the median and writes outputs/bench/log_step.json.
"""
from __future__ import annotations

import argparse
import statistics
import tempfile
import time

import _harness

_harness.apply_process_settings()  # before torch loads


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--steps", type=int, default=300)
    p.add_argument("--every", type=int, default=10, help="trainer.log_every_n_steps")
    p.add_argument("--out", default=str(_harness.OUTPUTS / "log_step.json"))
    args = p.parse_args()
    from segs.config import compose
    from segs.modules.gaussian_mapper import GaussianMapperModule
    from segs.train import build, step_batches

    times: list[float] = []
    log_step = GaussianMapperModule._log_step

    def timed(self, *a, **k):
        t = time.perf_counter()
        log_step(self, *a, **k)
        times.append((time.perf_counter() - t) * 1000.0)

    GaussianMapperModule._log_step = timed
    with tempfile.TemporaryDirectory() as out:
        cfg = compose([f"trainer.max_steps={args.steps}", f"trainer.log_every_n_steps={args.every}", "eval.enabled=false",
                       "callbacks.periodic_checkpoint.every_n_steps=0", "callbacks.image_logger.every_n_steps=0",
                       "slam=known_poses", "trainer.enable_progress_bar=false", "~callbacks.progress_bar"],
                      config_name="train", output_dir=out)  # fmt: skip
        t = build(cfg)
        t0 = time.perf_counter()
        t.trainer.fit(t.module, step_batches(args.steps))
        fit_s = time.perf_counter() - t0
    med = statistics.median(times)
    print(f"{len(times)} written steps of {args.steps}: {med:.2f} ms each (median; mean {statistics.fmean(times):.2f}), "
          f"fit {fit_s:.1f} s")  # fmt: skip
    _harness.write_json(args.out, {**_harness.record(), "args": vars(args), "written_steps": len(times), "ms_median": med,
                                   "ms": times, "fit_s": fit_s})  # fmt: skip


if __name__ == "__main__":
    main()
