"""Interrupt and resume, atomic checkpoints, determinism and the memory bound."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from conftest import TINY
from segs.callbacks.checkpoint import save_atomic
from segs.train import run


def _cli(args: list[str], **kw) -> subprocess.Popen:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return subprocess.Popen([sys.executable, "-m", "segs.train", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=env, **kw)  # fmt: skip


@pytest.mark.parametrize("sig,code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_signal_stops_at_a_step_boundary_and_the_run_resumes(tmp_path, sig, code):
    out = tmp_path / "run"
    base = TINY + ["trainer.max_steps=400", f"hydra.run.dir={out}", "callbacks.periodic_checkpoint.every_n_steps=10"]
    proc = _cli(base)
    ckpt = out / "checkpoints" / "last.ckpt"
    deadline = time.time() + 120
    while not ckpt.exists() and time.time() < deadline and proc.poll() is None:
        time.sleep(0.2)
    assert ckpt.exists(), proc.communicate()[1][-2000:]
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == code, err[-2000:]
    assert "resume with the same command plus" in err and "Traceback" not in err
    assert (out / "trajectory_partial.txt").stat().st_size > 0
    assert not (out / "metrics.json").exists()  # nothing that looks finished
    step = torch.load(ckpt, weights_only=False)["global_step"]
    assert 10 <= step < 400

    resumed = subprocess.run([sys.executable, "-m", "segs.train", *base, f"ckpt_path={ckpt}", "trainer.max_steps=60"]
                             if step < 60 else [sys.executable, "-m", "segs.train", *base, f"ckpt_path={ckpt}", f"trainer.max_steps={step + 20}"],
                             capture_output=True, text=True, timeout=300)  # fmt: skip
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["iterations"] == max(60, step + 20) and metrics["status"] == "finished"


class _Boom(RuntimeError):
    pass


def test_checkpoint_write_is_atomic(tmp_path):
    path = tmp_path / "last.ckpt"
    path.write_bytes(b"previous checkpoint")

    class Trainer:
        def save_checkpoint(self, p):
            Path(p).write_bytes(b"half a checkp")  # killed mid-write
            raise _Boom()

    with pytest.raises(_Boom):
        save_atomic(Trainer(), path)
    assert path.read_bytes() == b"previous checkpoint"


def test_fixed_seed_gives_the_same_run(tiny_cfg, tmp_path):
    a = run(tiny_cfg("trainer.max_steps=50", "seed=3", out=tmp_path / "a"))
    b = run(tiny_cfg("trainer.max_steps=50", "seed=3", out=tmp_path / "b"))
    assert a["anchors"] == b["anchors"] and a["keyframes"] == b["keyframes"]
    for key in ("psnr", "ssim", "ate_rmse_m"):
        assert a[key] == pytest.approx(b[key], abs=1e-4), key


def test_long_run_stays_under_the_memory_limit_and_the_anchor_cap(tiny_cfg, tmp_path):
    from segs.callbacks.memory import rss_mb

    limit = rss_mb() + 600
    m = run(tiny_cfg("data.n_frames=150", "trainer.max_steps=60", "eval.holdout_every=0", "model.max_anchors=1500", f"limits.max_rss_mb={limit:.0f}",
                     "callbacks.memory_guard.every_n_steps=5", out=tmp_path / "long"))  # fmt: skip
    assert m["anchors"] <= 1500 and m["frames"] == 150


def test_exceeding_the_memory_limit_stops_cleanly(tiny_cfg, tmp_path, capsys):
    from segs.config import user_errors_exit

    with pytest.raises(SystemExit) as exc:
        with user_errors_exit():
            run(tiny_cfg("limits.max_rss_mb=50", out=tmp_path / "small"))
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "limits.max_rss_mb=50" in err[0]
    assert (tmp_path / "small" / "checkpoints" / "last.ckpt").exists()
    assert not (tmp_path / "small" / "metrics.json").exists()
