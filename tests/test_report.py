"""segs.report on fake run folders: table rows match the runs, charts are written, crashes counted."""
from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from segs.report import collect, write_report
from segs.report.__main__ import main
from segs.report.charts import pareto_front
from segs.report.table import stability_table

METRICS = {"psnr": 20.0, "ssim": 0.7, "lpips": None, "test_views": 5, "active_gaussians": 900.0, "ate_rmse_m": 0.004,
           "iterations": 300, "wall_time_s": 60.0, "mapping_time_s": 50.0, "iterations_per_s": 6.0,
           "tracking_fps": 12.5, "frames": 60, "frames_tracked": 60, "tracked_fraction": 1.0, "lost_frames": 0,
           "anchors": 100, "gaussians": 1000, "params": 7100, "model_mb": 0.0284, "status": "finished"}  # fmt: skip


def fake_run(path: Path, overrides: list[str], metrics: dict | None = None, choices: dict | None = None,
             stress: dict | None = None, failure: str | None = None) -> Path:  # fmt: skip
    """A Hydra run folder as segs.train leaves it (metrics None: a crashed job)."""
    hydra = path / ".hydra"
    hydra.mkdir(parents=True)
    (hydra / "overrides.yaml").write_text(yaml.safe_dump(overrides))
    all_choices = {"experiment": "synthetic", "model": "segs", "slam": "orb", **(choices or {})}
    (hydra / "hydra.yaml").write_text(yaml.safe_dump({"hydra": {"runtime": {"choices": all_choices}}}))
    data = {"_target_": "x", "sensor": "${sensor.mode}"} | ({"stress": stress} if stress else {})
    (hydra / "config.yaml").write_text(yaml.safe_dump({"data": data, "paths": {"output_dir": "${hydra:runtime.output_dir}"}}))
    if metrics is not None:
        (path / "metrics.json").write_text(json.dumps({**METRICS, **metrics}))
    if failure:
        (path / "job_failed.txt").write_text(failure + "\n\nTraceback ...\n")
    return path


def _table_rows(md: str) -> list[str]:
    lines = md.split("## Runs", 1)[1].split("\n## ", 1)[0].splitlines()
    return [ln for ln in lines if ln.startswith("| ") and not ln.startswith("| run ")]


def test_two_runs_give_the_table_and_the_charts(tmp_path):
    sweep = tmp_path / "sweep"
    fake_run(sweep / "0", ["+sweep=speed_accuracy", "trainer.max_steps=100"], {"psnr": 18.0, "iterations": 100, "mapping_time_s": 20.0})
    fake_run(sweep / "1", ["+sweep=speed_accuracy", "trainer.max_steps=300"], {"psnr": 21.5, "lpips": 0.25})
    written = write_report([sweep])
    for name in ("markdown", "csv", "speed_accuracy", "compactness"):
        assert written[name].is_file() and written[name].stat().st_size > 0, name
        assert written[name].parent == sweep
    assert "stability" not in written  # no stressed runs
    md = written["markdown"].read_text()
    rows = _table_rows(md)
    assert len(rows) == 2
    assert "max_steps=100" in rows[0] and "| 18.00 |" in rows[0] and "n/a" in rows[0]  # LPIPS null -> n/a
    assert "max_steps=300" in rows[1] and "| 21.50 |" in rows[1] and "| 0.250 |" in rows[1]
    assert "`+sweep=speed_accuracy`" in md and "2 jobs: 2 finished, 0 crashed" in md
    assert "![Speed vs accuracy](speed_accuracy.png)" in md
    assert len(written["csv"].read_text().strip().splitlines()) == 3


def test_a_run_without_metrics_is_a_crash_without_numbers(tmp_path):
    fake_run(tmp_path / "m" / "0", ["a=1"], {})
    fake_run(tmp_path / "m" / "1", ["a=2"], None, failure="RuntimeError: the frontend produced no training keyframe")
    fake_run(tmp_path / "m" / "2", ["a=3"], None)
    runs = collect([tmp_path / "m"])
    assert [r.status for r in runs] == ["finished", "failed", "no metrics"]
    md = write_report([tmp_path / "m"])["markdown"].read_text()
    assert "3 jobs: 1 finished, 2 crashed or unfinished" in md
    assert "RuntimeError: the frontend produced no training keyframe" in md
    crashed = [r for r in _table_rows(md) if "a=2" in r][0]
    assert "20.00" not in crashed and crashed.count("n/a") >= 10


def test_a_run_trained_without_evaluation_is_not_a_crash(tmp_path):
    fake_run(tmp_path / "m" / "0", ["a=1"], {})
    fake_run(tmp_path / "m" / "1", ["eval.enabled=false"], {"status": "not_evaluated", "psnr": None, "ssim": None})
    runs = collect([tmp_path / "m"])
    assert [r.status for r in runs] == ["finished", "not_evaluated"] and not any(r.crashed for r in runs)
    md = write_report([tmp_path / "m"])["markdown"].read_text()
    assert "2 jobs: 1 finished, 1 trained without evaluation (eval.enabled=false), 0 crashed" in md
    row = [r for r in _table_rows(md) if "eval.enabled=false" in r][0]
    assert "| not_evaluated |" in row and "20.00" not in row


def test_jobs_that_never_started_are_listed_from_multirun_yaml(tmp_path):
    sweep = tmp_path / "sweep"
    fake_run(sweep / "0", ["+x=1", "seed=0"], {})
    multirun = {"hydra": {"sweeper": {"_target_": "hydra._internal.core_plugins.basic_sweeper.BasicSweeper",
                                      "params": {"+x": "1,2"}}, "overrides": {"task": ["seed=0"]}}}  # fmt: skip
    (sweep / "multirun.yaml").write_text(yaml.safe_dump(multirun))
    runs = collect([sweep])
    assert [r.status for r in runs] == ["finished", "not started"] and runs[1].overrides == ["+x=2", "seed=0"]
    assert "1 never started" in write_report([sweep])["markdown"].read_text()
    fake_run(tmp_path / "rerun" / "0", ["+x=2", "seed=0"], {})  # the missing job, run again elsewhere
    assert [r.status for r in collect([sweep, tmp_path / "rerun"])] == ["finished", "finished"]
    fake_run(sweep / "1", ["+x=2", "seed=0"], None)  # killed with its sweep: superseded by the rerun
    runs = collect([sweep, tmp_path / "rerun"])
    assert [r.status for r in runs] == ["finished", "superseded by a rerun", "finished"]
    assert not any(r.crashed for r in runs)


def test_stability_chart_and_table_per_kind_and_level(tmp_path):
    sweep = tmp_path / "stab"
    fake_run(sweep / "0", ["s=0"], {"psnr": 25.0}, stress={"kind": "noise", "level": 0})
    fake_run(sweep / "1", ["s=1"], {"psnr": 22.0}, stress={"kind": "noise", "level": 8})
    fake_run(sweep / "2", ["s=2"], {"tracked_fraction": 0.5, "ate_rmse_m": 0.3}, stress={"kind": "noise", "level": 32})
    fake_run(sweep / "3", ["s=3"], {}, stress={"kind": "fast_motion", "level": 3})
    fake_run(sweep / "4", ["s=4"], None, stress={"kind": "fast_motion", "level": 7})
    fake_run(sweep / "5", ["s=5"], None, stress={"kind": "fast_motion", "level": 15}, failure="IndexError: boom")
    written = write_report([sweep], min_tracked=0.9, max_ate_m=0.05)
    assert written["stability"].stat().st_size > 0
    table = stability_table(collect([sweep]))
    noise = table.split("### noise", 1)[1].split("###", 1)[0]
    assert "noise 0 | noise 8 | noise 32" in noise and "| 32 | 0 |" in noise  # fails from level 32, no crash
    fast = table.split("### fast_motion", 1)[1]
    assert "**no metrics**" in fast and "**CRASH IndexError**" in fast and "| 7 | 2 |" in fast  # baseline joins all


def test_pareto_front_keeps_the_best_accuracy_per_cost():
    pts = [(10, 20.0), (20, 19.0), (30, 22.0), (5, 15.0), (30, 21.0), (40, 22.0)]
    assert pareto_front(pts) == [(5, 15.0), (10, 20.0), (30, 22.0)]


def test_cli_prints_the_files_and_rejects_a_missing_folder(tmp_path, capsys):
    fake_run(tmp_path / "run", ["a=1"], {})
    assert main([str(tmp_path / "run"), "--out", str(tmp_path / "out")]) == 0
    printed = capsys.readouterr().out.split()
    assert str(tmp_path / "out" / "report.md") in printed
    with pytest.raises(SystemExit) as err:
        main([str(tmp_path / "missing")])
    assert err.value.code == 2
