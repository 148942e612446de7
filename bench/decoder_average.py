"""The decoder average (docs/decisions/039-decoder-average.md): test-view PSNR at chosen steps of
one training run, rendered with the live decoders and with averages of several decays.

    python bench/decoder_average.py --steps 2025 2075 2125 2150 2175 2200 2250 3000 4000 5300
    python bench/decoder_average.py --dataset 7scenes --steps 500 1000 1500 2000 2500

One run of the dataset's experiment as bench/peers.py runs it (every frame fed before the first
step, `trainer.max_steps` = the coarse-to-fine schedule's floor, mapping.min_schedule_steps), the
run's own `model.decoder_average` set to 0: beside it this script keeps an average per
--decays value (segs.modules.decoder_average.DecoderAverage, updated after every step as the
model updates its own) and at each --steps step scores the test views' PSNR and SSIM
(segs.evaluation's render_test_views, as the evaluation does) with the live weights and with each average in place
of them. The training is the same for every column. Prints one row per step and the mean over
the steps (each scoring's per-view CSV in a temporary folder it names); JSON in
outputs/bench/decoder_average_<dataset>.json.
"""
from __future__ import annotations

import json
import tempfile
from pathlib import Path

import _harness

_harness.apply_process_settings()  # before torch loads

import lightning as L  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

DATASETS = {
    "sample": ["+experiment=sample"],
    "7scenes": ["+experiment=seven_scenes_rgbd", "slam=known_poses", f"data.root={_harness.SEVEN_SCENES}", "data.frames=[100,250]",
                "eval.holdout_every=8"],
}  # fmt: skip


class Scorer(L.Callback):
    """After every step: each average follows the live decoders; at `steps`: the test views scored
    with the live decoders and with each average put in their place (then the live ones back)."""

    def __init__(self, steps: list[int], decays: list[float], score):
        from segs.modules.decoder_average import DecoderAverage

        self.steps, self.decays, self.score = sorted(steps), decays, score
        self.make = DecoderAverage
        self.averages: dict[float, object] = {}
        self.rows: list[dict] = []

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        live = pl_module.model.decoders()
        if not self.averages:
            self.averages = {d: self.make(live, d) for d in self.decays}
        for avg in self.averages.values():
            avg.update(live)
        step = int(trainer.global_step)
        if step in self.steps:
            row = {"step": step, **self._scored("live", pl_module)}
            kept = {n: [p.detach().clone() for p in m.parameters()] for n, m in live.items()}
            with torch.no_grad():
                for d, avg in self.averages.items():
                    self._put(live, {n: list(m.parameters()) for n, m in avg.averaged.items()})
                    row.update(self._scored(str(d), pl_module))
                self._put(live, kept)
            self.rows.append(row)
            print("decoder_average: " + json.dumps({k: round(v, 4) if isinstance(v, float) else v for k, v in row.items()}), flush=True)
        if step >= self.steps[-1]:
            trainer.should_stop = True

    def _scored(self, column: str, pl_module) -> dict:
        """{column: test PSNR, column + " ssim": test SSIM} with the weights now in place."""
        psnr, ssim = self.score(pl_module)
        return {column: psnr, f"{column} ssim": ssim}

    @staticmethod
    def _put(live: dict, weights: dict) -> None:
        for name, module in live.items():
            for p, w in zip(module.parameters(), weights[name]):
                p.copy_(w)


def run(dataset: str, steps: list[int], decays: list[float]) -> dict:
    import time_to_quality as ttq

    out = Path(tempfile.mkdtemp(prefix="decoder_average_"))
    print(f"decoder_average: per-view PSNR of each scoring in {out}/eval_NNN/test_views.csv", flush=True)
    scorer = Scorer(steps, decays, None)
    overrides = DATASETS[dataset] + ["seed=0", "model.decoder_average=0"]
    ttq.run_scored_at_steps(overrides, max(steps), scorer, out)
    columns = ["live"] + [str(d) for d in decays]
    mean = {c: float(np.mean([r[c] for r in scorer.rows])) for c in columns}
    print("decoder_average: mean over the steps " + json.dumps({c: round(v, 3) for c, v in mean.items()}), flush=True)
    return {**_harness.record(), "dataset": dataset, "overrides": overrides, "rows": scorer.rows, "mean": mean}


def main() -> None:
    import time_to_quality as ttq

    ap = ttq.steps_parser(__doc__, DATASETS)
    ap.add_argument("--decays", type=float, nargs="+", default=[0.9, 0.97, 0.99])
    args = ap.parse_args()
    result = run(args.dataset, args.steps, args.decays)
    path = _harness.write_json(ttq.steps_record_path(args, "decoder_average"), result)
    print(f"decoder_average: {path}")


if __name__ == "__main__":
    main()
