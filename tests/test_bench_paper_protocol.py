"""bench/paper_protocol.py: the protocol's command, its summary of a run, and (slow) a whole run on
the bundled sample, a failing one writing nothing."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import load_bench

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def protocol():
    return load_bench("paper_protocol")


def test_the_command_is_the_users_segs_train_with_the_device_and_time_box(protocol, tmp_path):
    cmd = protocol.command("seven_scenes_rgbd", "cuda", 30000, 4.5, tmp_path, ["slam_mode=process"])
    assert cmd[1:4] == ["-m", "segs.train", "+experiment=seven_scenes_rgbd"]
    assert {"trainer.max_steps=30000", "mapping.num_downscales=0", "raster.backend=cuda", "trainer.accelerator=gpu",
            "trainer.max_time=00:00:04:30", f"hydra.run.dir={tmp_path}"} <= set(cmd) and cmd[-1] == "slam_mode=process"  # fmt: skip
    cpu = protocol.command("sample", "cpu", 300, None, tmp_path, [])
    assert not any(c.startswith(("raster.backend", "trainer.accelerator", "trainer.max_time")) for c in cpu)


def test_the_summary_gives_wall_time_per_step_and_the_paper_budget_at_that_rate(protocol):
    prov = {"slam_mode": "process", "compiled_step_code": True}
    metrics = {"iterations": 15000, "mapping_time_s": 300.0, "psnr": 30.0, "provenance": prov}
    row = protocol.summary(metrics, 360.0)
    assert row["wall_ms_per_step"] == pytest.approx(20.0) and row["minutes_for_paper_steps"] == pytest.approx(10.0)
    assert row["psnr"] == 30.0 and row["ate_rmse_m"] is None and row["command_wall_s"] == 360.0
    assert row["slam_mode"] == "process" and row["compiled_step_code"] is True
    assert protocol.summary({"iterations": 0}, 5.0)["wall_ms_per_step"] is None


def _bench(tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(ROOT / "bench" / "paper_protocol.py"), "--experiment", "sample", "--device", "cpu",
                           "--run-dir", str(tmp_path / "run"), "--out", str(tmp_path / "out.json"), *args],
                          capture_output=True, text=True, cwd=ROOT, timeout=600)  # fmt: skip


@pytest.mark.slow
def test_a_run_on_the_sample_records_its_figures(tmp_path):
    proc = _bench(tmp_path, "--steps", "20")
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = json.loads((tmp_path / "out.json").read_text())
    res = out["result"]
    assert res["iterations"] == 20 and res["test_views"] > 0 and res["psnr"] > 0 and res["device"] == "cpu"
    assert res["wall_ms_per_step"] > 0 and out["machine"] and out["command"][:2] == ["-m", "segs.train"]
    assert "20 of 20 steps" in proc.stdout


@pytest.mark.slow
def test_a_failing_run_exits_non_zero_and_writes_no_figures(tmp_path):
    proc = _bench(tmp_path, "--steps", "20", "--extra", "model.no_such_key=1")
    assert proc.returncode != 0 and "the run failed" in proc.stderr and "no_such_key" in proc.stderr
    assert not (tmp_path / "out.json").exists()
