"""bench/decoder_average.py and bench/render_filter.py: each column scores the test views with its
own weights (or render filter) in place, and what the run uses is back after each scoring (logic
only, with stand-ins for the model and the scorer)."""
from __future__ import annotations

import importlib
import sys
from pathlib import Path
from types import SimpleNamespace

import torch
from torch import nn

ROOT = Path(__file__).resolve().parents[1]


def _bench():
    if str(ROOT / "bench") not in sys.path:
        sys.path.insert(0, str(ROOT / "bench"))
    return importlib.import_module("decoder_average")


def test_each_column_scores_its_weights_and_the_live_weights_are_restored():
    bench = _bench()
    lin = nn.Linear(1, 1, bias=False)
    module = SimpleNamespace(model=SimpleNamespace(decoders=lambda: {"lin": lin}))
    score = lambda m: (float(m.model.decoders()["lin"].weight.detach()), 0.5)  # noqa: E731
    scorer = bench.Scorer([2, 3], [0.5], score)
    trainer = SimpleNamespace(global_step=0, should_stop=False)
    for step, w in enumerate([4.0, 8.0, 0.0], start=1):
        with torch.no_grad():
            lin.weight.fill_(w)
        trainer.global_step = step
        scorer.on_train_batch_end(trainer, module, None, None, step - 1)
    # the average starts at the weights after step 1 (4), then 0.5 / 0.5 with 8, then with 0
    assert scorer.rows == [{"step": 2, "live": 8.0, "live ssim": 0.5, "0.5": 6.0, "0.5 ssim": 0.5},
                           {"step": 3, "live": 0.0, "live ssim": 0.5, "0.5": 3.0, "0.5 ssim": 0.5}]  # fmt: skip
    assert float(lin.weight.detach()) == 0.0 and trainer.should_stop


def test_the_render_filter_bench_scores_each_factor_and_puts_the_trained_one_back():
    if str(ROOT / "bench") not in sys.path:
        sys.path.insert(0, str(ROOT / "bench"))
    bench = importlib.import_module("render_filter")
    module = SimpleNamespace(trained_factor=2, trained_area=9.0)
    scorer = bench.Scorer([5], [4, 1], lambda m: (float(m.trained_factor if m.trained_area is None else m.trained_area), 0.9))
    trainer = SimpleNamespace(global_step=5, should_stop=False)
    scorer.on_train_batch_end(trainer, module, None, None, 4)
    assert scorer.rows == [{"step": 5, "trained": 2, "drawn": 9.0, "drawn ssim": 0.9, "f4": 4.0, "f4 ssim": 0.9, "f1": 1.0,
                            "f1 ssim": 0.9}]  # fmt: skip
    assert (module.trained_factor, module.trained_area) == (2, 9.0) and trainer.should_stop
