"""bench/time_to_quality.py: the training clock, the curve points and the files it writes, on the
tiny synthetic scene with a budget of seconds (logic only: no timing is asserted)."""
from __future__ import annotations

import json
import math
import time
from pathlib import Path

import pytest

from conftest import TINY, load_bench

ROOT = Path(__file__).resolve().parents[1]
EVAL_SLEEP_S = 0.5  # added to every evaluation: a clock that counted it would overrun the fit's wall time


def _bench():
    return load_bench("time_to_quality")


def _slow(score):
    def slowed(module):
        time.sleep(EVAL_SLEEP_S)
        return score(module)

    return slowed


@pytest.mark.slow
def test_curve_points_clock_and_outputs(tmp_path):
    bench = _bench()
    # the benchmark deletes the bars / loggers itself (a second deletion is a Hydra error)
    tiny = [o for o in TINY if not o.startswith("~")]
    curve = bench.run_curve(tiny, budget=3.0, marks=[1.0, 2.0], out=tmp_path / "run", max_steps=None, warmup_s=1.0, wrap_score=_slow)
    points = curve["points"]
    assert len(points) >= 2
    seconds, steps = [p["seconds"] for p in points], [p["steps"] for p in points]
    assert all(a < b for a, b in zip(seconds, seconds[1:])) and all(a < b for a, b in zip(steps, steps[1:]))
    assert steps[-1] == curve["steps"] > 0 and curve["max_steps"] >= curve["steps"]
    assert curve["warmup_steps_per_s"] > 0 and 0 < curve["schedule_done"] <= 1
    assert all(math.isfinite(p["psnr"]) and 0 < p["ssim"] <= 1 and p["test_views"] > 0 for p in points)
    assert all(p["gaussians"] > 0 and p["peak_rss_mb"] > 0 for p in points)
    # evaluation is timed apart and never on the training clock: training + evaluation seconds
    # fit inside the wall time of fit, although every evaluation slept EVAL_SLEEP_S
    assert all(p["eval_s"] >= EVAL_SLEEP_S for p in points)
    assert curve["eval_s"] == sum(p["eval_s"] for p in points)
    assert curve["train_s"] + curve["eval_s"] <= curve["fit_wall_s"] + 1e-6
    assert curve["train_s"] >= seconds[-1] and curve["feed_s"] < seconds[0]

    record = {"machine": {"cpu": "test"}, "command": "test", "curves": [
        {"dataset": "synthetic", "method": m, "budget_s": 3.0, **curve} for m in ("segs", "plain_3dgs")]}
    out_json, png = tmp_path / "ttq.json", tmp_path / "ttq.png"
    bench.write_outputs(record, out_json, png)
    saved = json.loads(out_json.read_text())
    assert len(saved["points"]) == 2 * len(points)
    assert {"method", "dataset", "seconds", "steps", "psnr", "ssim", "anchors", "gaussians", "peak_rss_mb"} <= set(saved["points"][0])
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size < 150_000
    rows = bench.table(record["curves"]).splitlines()
    assert rows[1].startswith("|---") and "synthetic | segs" in rows[2] and "synthetic | plain_3dgs" in rows[3]
    assert bench.paced_steps(out_json, "synthetic", "segs", 3.0) == curve["steps"]
    assert bench.paced_steps(out_json, "synthetic", "segs", 600.0) is None
