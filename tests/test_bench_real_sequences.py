"""bench/real_sequences.py on the bundled EuRoC pairs: the table, absent sequences listed as
skipped, the JSON with the commit, and --compare's rule."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "bench" / "real_sequences.py"


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True, timeout=300, cwd=ROOT)


@pytest.mark.slow
def test_table_json_skipped_rows_and_compare(tmp_path):
    first = tmp_path / "first.json"
    run = _run("--only", "euroc", "kitti", "--shared-data", str(tmp_path / "absent"), "--out", str(first))
    assert run.returncode == 0, run.stderr
    assert "| EuRoC V1_01 20 pairs | stereo | 20/20 | 1 | 0.06 cm |" in run.stdout
    assert f"skipped: {tmp_path / 'absent' / 'kitti_odometry_51'} is absent" in run.stdout
    record = json.loads(first.read_text())
    assert len(record["code"]["commit"]) == 40 and record["jobs"] == 1
    assert record["rows"]["kitti_mono"]["skipped"] and record["rows"]["euroc_stereo"]["frames_tracked"] == 20
    # the same row again: ATE ratio 1 (deterministic), nothing worse
    run = _run("--only", "euroc", "--compare", str(first), "--out", str(tmp_path / "second.json"))
    assert run.returncode == 0, run.stderr
    cmp = json.loads((tmp_path / "second.json").read_text())["compare"]
    assert cmp["ratios"] == {"euroc_stereo": 1.0} and cmp["worse"] == []
