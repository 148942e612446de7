"""bench/side_by_side.py: two frontends released together, on the small synthetic sequence, this
checkout against itself (logic only: no timing is asserted)."""
from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "bench" / "side_by_side.py"


@pytest.mark.slow
def test_both_sides_run_the_same_frames_and_report_ratios(tmp_path):
    out = tmp_path / "sbs.json"
    res = subprocess.run([sys.executable, str(SCRIPT), "--against", str(ROOT / "src"), "--sequence", "synthetic",
                          "--pairs", "2", "--out", str(out)], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    r = json.loads(out.read_text())
    assert len(r["pairs"]) == 2 and r["this"]["commit"] == r["reference"]["commit"]
    for pair in r["pairs"]:
        this, ref = pair["this"], pair["reference"]
        # the same code on the same frames: the deterministic frontend gives the same map
        assert this["frames"] == ref["frames"] == 30 and this["keyframes"] == ref["keyframes"] > 1
        assert this["ate_cm"] == ref["ate_cm"] < 5
        assert all(this[f"{k}_s"] > 0 for k in ("features", "track", "mapping"))
    ratios = r["ratio_this_over_reference"]
    assert all(math.isfinite(v) and v > 0 for v in ratios.values()) and len(r["total_ratio_per_pair"]) == 2
    assert "whole run" in res.stdout


def test_a_reference_without_segs_is_one_line_and_a_nonzero_exit(tmp_path):
    res = subprocess.run([sys.executable, str(SCRIPT), "--against", str(tmp_path), "--sequence", "synthetic"],
                         capture_output=True, text=True, timeout=60)
    assert res.returncode != 0 and f"--against {tmp_path}: no segs package there" in res.stderr
    assert "Traceback" not in res.stderr and len(res.stderr.strip().splitlines()) == 1
