"""Interrupt and resume, atomic checkpoints, determinism and the memory bound."""
from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import lightning as L
import pytest
import torch

from conftest import TINY
from segs.callbacks.checkpoint import save_atomic
from segs.train import run


def _cli(args: list[str], **kw) -> subprocess.Popen:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return subprocess.Popen([sys.executable, "-m", "segs.train", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=env, **kw)  # fmt: skip


@pytest.mark.slow
@pytest.mark.parametrize("sig,code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_signal_stops_at_a_step_boundary_and_the_run_resumes(tmp_path, sig, code):
    out = tmp_path / "run"
    base = TINY + ["trainer.max_steps=400", f"hydra.run.dir={out}", "callbacks.periodic_checkpoint.every_n_steps=10",
                   "callbacks.periodic_checkpoint.min_interval_s=0"]
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

    steps = 60 if step < 60 else step + 20
    resumed = subprocess.run([sys.executable, "-m", "segs.train", *base, f"ckpt_path={ckpt}", f"trainer.max_steps={steps}"],
                             capture_output=True, text=True, timeout=300)  # fmt: skip
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["iterations"] == steps and metrics["status"] == "finished"


class SignalProbe(L.Callback):
    """Records who handles SIGINT / SIGTERM at each step (test_the_interrupt_is_the_one_signal_handler)."""

    seen: list = []

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        SignalProbe.seen.append((signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)))


def test_the_interrupt_is_the_one_signal_handler(tiny_cfg):
    """Lightning registers a SIGTERM handler of its own in fit (SIGTERMException, exit 0): during
    training both signals go to segs.callbacks.interrupt only, and are given back after the run."""
    from segs.callbacks.interrupt import GracefulInterrupt

    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    SignalProbe.seen = []
    run(tiny_cfg("trainer.max_steps=5", "+callbacks.probe._target_=test_reliability.SignalProbe", "eval.enabled=false"))
    handlers = {h for pair in SignalProbe.seen for h in pair}
    assert len(SignalProbe.seen) == 5 and len(handlers) == 1
    (handler,) = handlers
    assert isinstance(handler.__self__, GracefulInterrupt) and handler.__name__ == "_handler"
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before


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


def test_run_checkpoints_are_written_straight_to_their_file(tiny_cfg, tmp_path, monkeypatch):
    """segs.train's trainer writes with DirectCheckpointIO: torch.save to the (temporary) file,
    without Lightning's in-memory copy of the whole checkpoint."""
    import io

    from segs.callbacks.checkpoint import DirectCheckpointIO
    from segs.train import build

    trainer = build(tiny_cfg(out=tmp_path / "run")).trainer
    assert isinstance(trainer.strategy.checkpoint_io, DirectCheckpointIO)
    saved = []
    monkeypatch.setattr(torch, "save", lambda obj, f, **kw: saved.append(f))
    trainer.strategy.checkpoint_io.save_checkpoint({"step": torch.arange(3)}, tmp_path / "sub" / "x.ckpt")
    assert saved == [str(tmp_path / "sub" / "x.ckpt")] and not isinstance(saved[0], io.BytesIO)
    monkeypatch.undo()
    DirectCheckpointIO().save_checkpoint({"step": torch.arange(3)}, tmp_path / "x.ckpt")
    assert torch.equal(torch.load(tmp_path / "x.ckpt")["step"], torch.arange(3))


def test_fixed_seed_gives_the_same_run(tiny_cfg, tmp_path):
    a = run(tiny_cfg("trainer.max_steps=50", "seed=3", out=tmp_path / "a"))
    b = run(tiny_cfg("trainer.max_steps=50", "seed=3", out=tmp_path / "b"))
    assert a["anchors"] == b["anchors"] and a["keyframes"] == b["keyframes"]
    for key in ("psnr", "ssim", "ate_rmse_m"):
        assert a[key] == pytest.approx(b[key], abs=1e-4), key


def test_long_run_stays_under_the_memory_limit_and_the_anchor_cap(tiny_cfg, tmp_path):
    from segs.callbacks.memory import rss_mb

    limit = rss_mb() + 600
    m = run(tiny_cfg("data.n_frames=150", "trainer.max_steps=60", "eval.holdout_every=0", "model.max_anchors=1500",
                     f"limits.max_rss_mb={limit:.0f}", "callbacks.memory_guard.every_n_steps=5", out=tmp_path / "long"))  # fmt: skip
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


def test_a_failed_checkpoint_write_removes_its_temporary_file(tmp_path):
    class Trainer:
        def save_checkpoint(self, p):
            Path(p).write_bytes(b"half a checkp")
            raise OSError(28, "No space left on device")

    with pytest.raises(OSError):
        save_atomic(Trainer(), tmp_path / "final.ckpt")
    assert list(tmp_path.iterdir()) == []


# -- run folders ------------------------------------------------------------------------------


def _lines(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.strip() and "Warning" not in line and "warn(" not in line]


@pytest.mark.slow
def test_a_folder_holding_a_finished_run_is_refused_before_anything_is_written(tmp_path):
    out = tmp_path / "run"
    first = subprocess.run([sys.executable, "-m", "segs.train", *TINY, "trainer.max_steps=5", f"hydra.run.dir={out}"],
                           capture_output=True, text=True, timeout=300)  # fmt: skip
    assert first.returncode == 0, first.stderr[-2000:]
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    again = subprocess.run([sys.executable, "-m", "segs.train", *TINY, "trainer.max_steps=7", f"hydra.run.dir={out}"],
                           capture_output=True, text=True, timeout=300)  # fmt: skip
    assert again.returncode == 2 and _lines(again.stderr) == [
        f"error: hydra.run.dir={out} already holds a finished run (metrics.json); give this run another folder"]
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before  # overrides.yaml, log, metrics untouched


@pytest.mark.slow
def test_a_folder_another_run_is_writing_into_is_refused(tmp_path):
    # this test process holds the folder as a running segs.train does (the same flock)
    from segs.run_folder import claim, release

    out = tmp_path / "run"
    claim(out)
    try:
        second = subprocess.run([sys.executable, "-m", "segs.train", *TINY, f"hydra.run.dir={out}"], capture_output=True,
                                text=True, timeout=300)  # fmt: skip
    finally:
        release(out)
    assert second.returncode == 2 and _lines(second.stderr) == [
        f"error: hydra.run.dir={out}: process {os.getpid()} on {socket.gethostname()} is running in this folder; "
        "give this run another folder"]
    assert [p.name for p in out.iterdir()] == [".segs.lock"]  # nothing of the second run written


def test_default_run_folders_differ_within_a_second():
    from segs.config import compose

    cfg = compose([])
    name = Path(cfg.hydra.run.dir).name
    assert len(name.split("-")[-1]) == 6 and name.split("-")[-1].isdigit(), name  # microseconds


def test_a_checkpoint_in_the_folder_lets_a_run_resume_there_and_nothing_else(tmp_path):
    from segs.errors import ConfigError
    from segs.run_folder import claim, release

    (tmp_path / "checkpoints").mkdir()
    (tmp_path / "checkpoints" / "last.ckpt").write_bytes(b"x")
    with pytest.raises(ConfigError, match="already holds an unfinished run .*resume it with ckpt_path="):
        claim(tmp_path)
    claim(tmp_path, str(tmp_path / "checkpoints" / "last.ckpt"))
    release(tmp_path)
    (tmp_path / "other").mkdir()
    claim(tmp_path / "other")  # a fresh folder, or one left by a run that failed at start (.hydra/ only)
    release(tmp_path / "other")


# -- the end of a run: final checkpoint, signals after fit ---------------------------------------


def test_a_final_checkpoint_that_cannot_be_written_loses_no_result(tiny_cfg, tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    (out / "checkpoints").write_text("a file where the checkpoint folder should be")  # mkdir fails
    m = run(tiny_cfg("callbacks.periodic_checkpoint.every_n_steps=0", out=out))
    assert m["status"] == "finished" and m["final_checkpoint"] is None and "FileExistsError" in m["checkpoint_note"]
    assert json.loads((out / "metrics.json").read_text())["checkpoint_note"] == m["checkpoint_note"]
    assert (out / "trajectory.txt").stat().st_size > 0 and (out / "point_cloud.ply").is_file()
    assert not list(out.rglob("*.tmp"))


def test_a_run_without_evaluation_says_so(tiny_cfg, tmp_path):
    m = run(tiny_cfg("eval.enabled=false", "callbacks.periodic_checkpoint.every_n_steps=0", out=tmp_path / "run"))
    assert m["status"] == "not_evaluated" and m["psnr"] is None and m["test_views"] == 0
    assert m["iterations"] == 40 and m["anchors"] > 0 and (tmp_path / "run" / "metrics.json").is_file()


def _stopped(cfg, capsys, code: int = 130) -> str:
    with pytest.raises(SystemExit) as exc:
        run(cfg)
    assert exc.value.code == code
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return err


@pytest.mark.parametrize("sig,code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_a_signal_during_the_evaluation_stops_cleanly(tiny_cfg, tmp_path, capsys, monkeypatch, sig, code):
    import segs.evaluation

    real = segs.evaluation.psnr

    def psnr_then_signal(*a):
        signal.raise_signal(sig)
        return real(*a)

    monkeypatch.setattr(segs.evaluation, "psnr", psnr_then_signal)
    out = tmp_path / "run"
    err = _stopped(tiny_cfg("callbacks.periodic_checkpoint.every_n_steps=0", out=out), capsys, code)
    assert f"segs: stopped by {signal.Signals(sig).name}; no metrics.json written" in err
    final = out / "checkpoints" / "final.ckpt"
    assert f"ckpt_path={final}" in err and final.is_file() and not (out / "metrics.json").exists()
    monkeypatch.setattr(segs.evaluation, "psnr", real)
    m = run(tiny_cfg(f"ckpt_path={final}", "callbacks.periodic_checkpoint.every_n_steps=0", out=out))  # evaluate it
    assert m["status"] == "finished" and m["iterations"] == 40


def _signal_in_final_save(monkeypatch, times: int) -> None:
    real = L.Trainer.save_checkpoint

    def save(self, path, *a, **kw):
        if Path(path).name.startswith("final"):
            Path(path).write_bytes(b"x" * 1000)  # part of the file is on disk
            for _ in range(times):
                signal.raise_signal(signal.SIGINT)
        return real(self, path, *a, **kw)

    monkeypatch.setattr(L.Trainer, "save_checkpoint", save)


def test_ctrl_c_during_the_final_checkpoint_lets_it_finish_then_stops(tiny_cfg, tmp_path, capsys, monkeypatch):
    _signal_in_final_save(monkeypatch, times=1)
    out = tmp_path / "run"
    err = _stopped(tiny_cfg("callbacks.periodic_checkpoint.every_n_steps=0", out=out), capsys)
    assert "stopping after the checkpoint is written" in err and "evaluate it with the same command plus" in err
    assert torch.load(out / "checkpoints" / "final.ckpt", weights_only=False)["global_step"] == 40
    assert not (out / "metrics.json").exists() and not list(out.rglob("*.tmp"))


def test_a_second_ctrl_c_during_a_checkpoint_write_leaves_no_temporary_file(tiny_cfg, tmp_path, capsys, monkeypatch):
    _signal_in_final_save(monkeypatch, times=2)
    out = tmp_path / "run"
    err = _stopped(tiny_cfg("callbacks.periodic_checkpoint.every_n_steps=0", out=out), capsys)
    assert "stopped by SIGINT; no metrics.json written; nothing was saved since the last checkpoint" in err
    assert not list(out.rglob("*.tmp")) and not list(out.rglob("*.ckpt")) and not (out / "metrics.json").exists()


# -- memory ------------------------------------------------------------------------------------


def test_memory_figures_share_one_unit():
    from segs.callbacks.memory import peak_rss_mb, rss_mb

    now = rss_mb()
    assert now <= peak_rss_mb() < 1.2 * max(now, peak_rss_mb())  # the peak is never below the current RSS


def test_the_memory_guard_watches_tracking_training_and_evaluation(tiny_cfg, tmp_path, monkeypatch):
    from segs.callbacks.memory import MemoryGuard

    seen = []
    monkeypatch.setattr(MemoryGuard, "check", lambda self, trainer, where, save=True: seen.append(where))
    run(tiny_cfg("callbacks.slam_bridge.min_initial_keyframes=5", "callbacks.memory_guard.every_n_steps=10",
                 "callbacks.slam_bridge.feed_until=1.0", out=tmp_path / "run"))  # fmt: skip
    kinds = {w.split(" ", 2)[0] + " " + w.split(" ", 2)[1] for w in seen}
    assert {"while tracking", "at step", "at test"} <= kinds, seen
