"""The sweeps of conf/sweep: every job composes; a tiny 2-job multirun completes, records, reports."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import TINY
from segs.config import CONF_DIR, REPO_ROOT, compose
from segs.report import collect
from segs.report.runs import _expand

SWEEPS = ["speed_accuracy", "compactness", "stability"]
# the ORB frontend config may not exist yet: the sweeps are composed with the known-poses one
SLAM = [] if (CONF_DIR / "slam" / "orb.yaml").is_file() else ["slam=known_poses"]
# the tiny multirun: TINY with fewer steps, quiet sweep settings, and 2 jobs
TINY_SWEEP = [o for o in TINY if o not in ("~callbacks.progress_bar",)] + ["+sweep=common", "trainer.max_steps=6"]


def _sweep_jobs(name: str) -> list[list[str]]:
    """Every job's overrides of `python -m segs.train -m +sweep=NAME` (Hydra's own expansion)."""
    cfg = compose([f"+sweep={name}"] + SLAM, output_dir="/tmp")
    params = [f"{k}={v}" for k, v in cfg.hydra.sweeper.params.items()]
    return _expand(params + [f"+sweep={name}"] + SLAM)


def _covering(jobs: list[list[str]], skip: str = "+data.stress=") -> list[list[str]]:
    """A few jobs holding every swept value at least once (data.stress values are checked apart)."""
    chosen, seen = [], set()
    for job in jobs:
        new = {o for o in job if not o.startswith(skip)} - seen
        if new:
            chosen.append(job)
            seen |= new
    return chosen


@pytest.mark.parametrize("name", SWEEPS)
def test_every_swept_value_composes_with_its_method_and_experiment(name, tmp_path):
    jobs = _sweep_jobs(name)
    assert len(jobs) >= 10
    models = set()
    for job in _covering(jobs):
        cfg = compose(job, output_dir=str(tmp_path))
        models.add(cfg.model._target_.rsplit(".", 1)[1])
        assert cfg.hydra.sweep.dir.startswith(f"{cfg.paths.log_dir}/sweeps/{name}/")
        assert "record_failure" in cfg.hydra.callbacks and not cfg.get("logger")
        if any("plain_3dgs" in o for o in job):
            assert cfg.model._target_.endswith("PlainGaussians"), job  # the method wins over the experiment
    assert "SegsModel" in models and "PlainGaussians" in models


def test_stability_sweep_covers_every_stress_kind_with_rising_levels():
    from segs.data.stress import KINDS, check

    jobs = _sweep_jobs("stability")
    stresses = [o.split("=", 1)[1] for job in jobs for o in job if o.startswith("+data.stress=")]
    kinds = {s.split("kind:")[1].split(",")[0] for s in stresses}
    assert kinds == set(KINDS)
    cfg = compose(["+sweep=stability"] + SLAM, output_dir="/tmp")
    for stress in set(stresses):
        kind, level = stress.strip("{}").split(",")
        check(kind.split(":")[1], float(level.split(":")[1]), cfg.sensor.mode)  # all valid for the experiment


def _multirun(tmp_path: Path, *overrides: str, launcher: str, base: list[str] = TINY_SWEEP) -> subprocess.CompletedProcess:
    args = [sys.executable, "-m", "segs.train", "-m", *base, *overrides, f"hydra/launcher={launcher}",
            f"hydra.sweep.dir={tmp_path / 'sweep'}"]  # fmt: skip
    return subprocess.run(args, cwd=tmp_path, capture_output=True, text=True, timeout=240)


@pytest.mark.slow
def test_tiny_two_job_multirun_completes_and_reports(tmp_path):
    # the joblib launcher is a dependency of segs: this is the parallel sweep users run
    proc = _multirun(tmp_path, "+data.stress={kind:noise,level:0},{kind:noise,level:8}", launcher="local")
    assert proc.returncode == 0, proc.stderr[-3000:]
    sweep = tmp_path / "sweep"
    for job in ("0", "1"):
        m = json.loads((sweep / job / "metrics.json").read_text())
        assert m["status"] == "finished" and m["iterations"] == 6
    md = (sweep / "report.md").read_text()  # written by the sweep's ReportOnMultirunEnd callback
    assert "2 jobs: 2 finished, 0 crashed" in md and "noise" in md
    assert all((sweep / f).stat().st_size > 0 for f in ("speed_accuracy.png", "compactness.png", "stability.png"))
    runs = collect([sweep])
    assert [r.stress for r in runs] == [("noise", 0.0), ("noise", 8.0)]
    # the same sweep folder again: refused before any job runs, the first sweep untouched
    again = _multirun(tmp_path, "+data.stress={kind:noise,level:0},{kind:noise,level:8}", launcher="local")
    assert again.returncode == 2 and again.stderr.strip().splitlines()[-1] == (
        f"error: hydra.sweep.dir={sweep} already holds a sweep (multirun.yaml); give this run another folder")
    assert json.loads((sweep / "0" / "metrics.json").read_text())["iterations"] == 6


@pytest.mark.slow
def test_a_failing_job_does_not_hide_the_other_and_is_recorded(tmp_path):
    # job 0 raises when Lightning's Trainer is built (a cheap failure that is not a user-input error:
    # those exit the whole process, see docs/experiments.md)
    proc = _multirun(tmp_path, "trainer.accelerator=bogus,cpu", launcher="basic")
    assert proc.returncode != 0  # Hydra re-raises the failure after the batch
    sweep = tmp_path / "sweep"
    assert "invalid accelerator name" in (sweep / "0" / "job_failed.txt").read_text().splitlines()[0]
    assert (sweep / "1" / "metrics.json").is_file()
    report = subprocess.run([sys.executable, "-m", "segs.report", str(sweep)], cwd=REPO_ROOT, capture_output=True,
                            text=True, timeout=120)  # fmt: skip
    assert report.returncode == 0, report.stderr
    md = (sweep / "report.md").read_text()
    assert "2 jobs: 1 finished, 1 crashed" in md and "invalid accelerator name" in md


@pytest.mark.slow
def test_a_job_whose_tracking_fails_is_a_result_not_a_crash(tmp_path):
    # every frame blank: the ORB frontend tracks nothing. A single run exits 2 with one line;
    # inside a sweep the job returns, metrics.json says "tracking_failed" and the sweep goes on.
    blank = ["slam=orb", "data.blank_frames=[[0,14]]"]
    tiny_orb = [o for o in TINY_SWEEP if not o.startswith("slam")]
    single = subprocess.run([sys.executable, "-m", "segs.train", *tiny_orb, *blank, f"hydra.run.dir={tmp_path / 'one'}"],
                            cwd=tmp_path, capture_output=True, text=True, timeout=240)  # fmt: skip
    assert single.returncode == 2 and single.stderr.strip().splitlines()[-1].startswith("error: data: no training keyframe")
    assert json.loads((tmp_path / "one" / "metrics.json").read_text())["status"] == "tracking_failed"
    proc = _multirun(tmp_path, *blank, launcher="basic", base=tiny_orb)
    assert proc.returncode == 0, proc.stderr[-3000:]
    m = json.loads((tmp_path / "sweep" / "0" / "metrics.json").read_text())
    assert m["status"] == "tracking_failed" and m["tracked_fraction"] == 0 and m["psnr"] is None
    md = (tmp_path / "sweep" / "report.md").read_text()
    assert "1 jobs: 0 finished, 1 tracking failed" in md and "0 crashed" in md
