"""bench/_harness.py: the shared data lookup and its override, the record, the timer, medians and
the JSON writer every bench script uses (logic only: no timing is asserted)."""
from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

import segs
from conftest import load_bench

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "bench"
# analyses whose results do not depend on the machine (no timings), headline.py, which reads the
# runs' own records, and viewer_library.py, which prints and writes nothing: no machine record
NO_RECORD = {"ate_diagnostics.py", "calibrate_7scenes.py", "place_recognition.py", "seven_scenes_signal.py", "headline.py",
             "viewer_library.py"}


@pytest.fixture(scope="module")
def harness():
    return load_bench("_harness", "bench_harness")


def test_shared_data_is_beside_the_checkout_unless_the_environment_says_where(tmp_path):
    code = "import _harness; print(_harness.SEVEN_SCENES)"
    env = {k: v for k, v in os.environ.items() if k != "SEGS_SHARED_DATA"}
    default = subprocess.run([sys.executable, "-c", code], cwd=BENCH, env=env, capture_output=True, text=True, check=True)
    assert Path(default.stdout.strip()) == ROOT.parent / "shared" / "data" / "7scenes_redkitchen_0000_0599"
    moved = subprocess.run([sys.executable, "-c", code], cwd=BENCH, env={**env, "SEGS_SHARED_DATA": str(tmp_path)},
                           capture_output=True, text=True, check=True)  # fmt: skip
    assert Path(moved.stdout.strip()) == tmp_path / "7scenes_redkitchen_0000_0599"


def test_record_names_the_machine_and_the_commit(harness):
    rec = harness.record()
    assert rec["machine"]["cores"] >= 1 and rec["machine"]["cpu"] and len(rec["machine"]["load_avg"]) == 3
    assert Path(rec["code"]["source"]) == Path(segs.__file__).resolve().parent  # the segs that runs
    assert set(rec["code"]) == {"source", "commit", "dirty"} and rec["time"]
    if rec["code"]["commit"] is not None:
        assert harness.short_commit(ROOT).split("+")[0] == rec["code"]["commit"][:7]
    assert harness.short_commit(Path("/")) == "?"


def test_median_seconds_runs_setup_before_each_timed_call(harness):
    calls = []
    t = harness.median_seconds(lambda: calls.append("fn"), 3, warmup=1, setup=lambda: calls.append("setup"))
    assert calls == ["fn"] + ["setup", "fn"] * 3 and t >= 0


def test_medians_take_measurements_and_keep_counts(harness):
    rows = [{"ms": 3.0, "kfs": 10, "name": "a", "none": None}, {"ms": 1.0, "kfs": 11, "name": "b", "none": None},
            {"ms": 2.0, "kfs": 12, "name": "c", "none": None}]  # fmt: skip
    assert harness.medians(rows) == {"ms": 2.0, "kfs": 10, "name": "a", "none": None}


def test_write_json_creates_the_folder_and_leaves_no_temporary(harness, tmp_path):
    path = harness.write_json(tmp_path / "a" / "b.json", {"x": [1, 2]})
    assert json.loads(path.read_text()) == {"x": [1, 2]} and os.listdir(path.parent) == ["b.json"]


def _calls_in_order(path: Path) -> list[str]:
    """Top-level statements of a script: 'apply' for the settings call, module names for imports."""
    out = []
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, ast.Expr) and "apply_process_settings" in ast.unparse(node):
            out.append("apply")
        elif isinstance(node, ast.Import):
            out += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module != "__future__":
            out.append(node.module)
    return out


@pytest.mark.parametrize("script", sorted(p.name for p in BENCH.glob("*.py") if not p.name.startswith("_")))
def test_bench_scripts_apply_the_settings_before_anything_but_the_standard_library(script):
    """A script that imports more than the standard library (segs, torch, numpy, ...) calls
    _harness.apply_process_settings() first (bench/headline.py only reads JSON: none)."""
    order = _calls_in_order(BENCH / script)
    stdlib = set(sys.stdlib_module_names) | {"_harness"}
    if "apply" not in order:
        assert all(m.split(".")[0] in stdlib for m in order), f"{script} does not call _harness.apply_process_settings()"
        return
    late = [m for m in order[: order.index("apply")] if m.split(".")[0] not in stdlib]
    assert not late, f"{script} imports {late} before applying the process settings"


@pytest.mark.parametrize("script", sorted(p.name for p in BENCH.glob("*.py") if not p.name.startswith("_")))
def test_bench_scripts_take_the_data_path_and_the_machine_record_from_the_harness(script):
    text = (BENCH / script).read_text()
    assert '"shared" / "data"' not in text, f"{script}: the shared data path is _harness.SHARED_DATA's"
    if script not in NO_RECORD:
        assert "_harness.record()" in text, f"{script}: the machine and commit come from _harness.record()"
