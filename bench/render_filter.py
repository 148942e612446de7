"""The render filter after a coarse-to-fine switch (docs/decisions/035-render-filter-of-the-trained-pixels.md):
test-view PSNR / SSIM at chosen steps of one run, rendered through the low-pass filter of each
training pixel size.

    python bench/render_filter.py --steps 2000 2025 2027 2030 2035 2040 2050 2075 2100 2150 2200
    python bench/render_filter.py --dataset 7scenes --steps 2025 2030 2050 2100

One run of the dataset's experiment as bench/peers.py runs it (every frame fed before the first
step, the 6,750-step schedule of the coarse-to-fine defaults: 1/4 size to step 2,025, 1/2 to
4,050; the datasets of bench/decoder_average.py); at each --steps step the test views are scored
(segs.evaluation's render_test_views) through the run's own filter ("drawn":
`mapping.render_filter: trained`, 0.3 px^2 x the training's pixel area averaged with
mapping.render_filter_decay) and through the filter of each --factors pixel size, 0.3 px^2 x
factor^2. The training is the same for every column. Prints one row per step; JSON in
outputs/bench/render_filter_<dataset>.json.
"""
from __future__ import annotations

import json
import tempfile
from pathlib import Path

import _harness

_harness.apply_process_settings()  # before torch loads

import lightning as L  # noqa: E402


class Scorer(L.Callback):
    """At `steps`: the test views scored as the run draws them and with the module's filter set to
    each of `factors` (then put back); rows {"step", "trained": the latest step's factor, "drawn",
    "drawn ssim", "f<k>", "f<k> ssim"}."""

    def __init__(self, steps: list[int], factors: list[int], score):
        self.steps, self.factors, self.score = sorted(steps), factors, score
        self.rows: list[dict] = []

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        step = int(trainer.global_step)
        if step in self.steps:
            kept = pl_module.trained_factor, pl_module.trained_area
            row = {"step": step, "trained": kept[0]}
            row["drawn"], row["drawn ssim"] = self.score(pl_module)  # the run's own filter
            for f in self.factors:
                pl_module.trained_factor, pl_module.trained_area = f, None
                row[f"f{f}"], row[f"f{f} ssim"] = self.score(pl_module)
            pl_module.trained_factor, pl_module.trained_area = kept
            self.rows.append(row)
            print("render_filter: " + json.dumps({k: round(v, 4) if isinstance(v, float) else v for k, v in row.items()}), flush=True)
        if step >= self.steps[-1]:
            trainer.should_stop = True


def main() -> None:
    import time_to_quality as ttq
    from decoder_average import DATASETS

    ap = ttq.steps_parser(__doc__, DATASETS)
    ap.add_argument("--factors", type=int, nargs="+", default=[4, 2, 1])
    args = ap.parse_args()
    out = Path(tempfile.mkdtemp(prefix="render_filter_"))
    scorer = Scorer(args.steps, args.factors, None)
    overrides = DATASETS[args.dataset] + ["seed=0"]
    ttq.run_scored_at_steps(overrides, max(args.steps), scorer, out)
    record = {**_harness.record(), "dataset": args.dataset, "overrides": overrides, "rows": scorer.rows}
    path = _harness.write_json(ttq.steps_record_path(args, "render_filter"), record)
    print(f"render_filter: {path}")


if __name__ == "__main__":
    main()
