"""`python -m segs.train [+experiment=NAME] [+ablation=NAME] [key=value ...]`

Tracks the sequence with the configured frontend, trains the Gaussian map on its keyframes,
evaluates the test views and writes metrics.json, the trajectory, renders, a PLY and the final
checkpoint into the Hydra run folder.
"""
from __future__ import annotations

if __name__ == "__main__":  # the program: process settings before torch loads (docs/decisions/028-process-settings.md)
    from segs import process_settings

    process_settings.apply()

import logging
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import hydra
import lightning as L
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from segs import process_settings
from segs.callbacks import GracefulInterrupt, MemoryGuard, SlamBridge, save_atomic
from segs.callbacks.checkpoint import DirectCheckpointIO
from segs.callbacks.interrupt import Interrupted
from segs.callbacks.run_record import RunRecord, check_resume, fingerprint, read_checkpoint
from segs.config import instantiate, make_sequence, make_source, user_errors_exit, validate
from segs.data.frame import Sequence
from segs.errors import DataError, TrackingFailed
from segs.eval_config import eval_config
from segs.evaluation import evaluate, write_not_evaluated, write_tracking_failed
from segs.modules.config import build_model, mapping_config, raster_config
from segs.modules.gaussian_mapper import GaussianMapperModule
from segs.pipeline.run_state import RunState
from segs.provenance import provenance
from segs.viewer.config import viewer_config

log = logging.getLogger("segs.train")


def step_batches(steps: int) -> range:
    """What trainer.fit iterates: Lightning's fit loop needs an iterable and runs one training
    step per item; the module samples its own training view, so the items are the step indices
    (no Dataset or DataLoader: nothing to load, and no seed drawn from any generator)."""
    return range(steps)


@dataclass
class TrainingRun:
    """One session of a segs.train run: what build() made, and the final checkpoint once written.

    interrupt: the run's one Ctrl-C / SIGTERM handler (segs.callbacks.interrupt), the first of
    the trainer's callbacks; record: times and fingerprint (RunRecord); guard: the memory guard,
    if configured; started: time.perf_counter() when the session started.
    """

    cfg: DictConfig
    out: Path
    sequence: Sequence
    state: RunState
    module: GaussianMapperModule
    bridge: SlamBridge
    trainer: L.Trainer
    interrupt: GracefulInterrupt
    record: RunRecord
    guard: MemoryGuard | None
    started: float
    final_checkpoint: str | None = None

    def execute(self) -> dict:
        """Fit, final checkpoint, the frames not fed yet, evaluation; -> metrics.json's dict.
        Between training and the evaluation the heap's free pages (the training steps' working
        set) go back to the kernel: the evaluation's own memory then adds to less than the
        training's peak (docs/decisions/029-peak-memory.md)."""
        self.fit()
        notes = self.save_final()
        process_settings.release_free_memory()
        return self.evaluate(notes)

    def fit(self) -> None:
        """trainer.fit; a tracking failure is recorded in metrics.json, then raised; a signal
        during fit ends the run with its exit status (after the checkpoint the handler wrote)."""
        try:
            # our checkpoints hold numpy arrays (frontend map, RNG states): they are the user's own files
            self.trainer.fit(self.module, step_batches(self.cfg.trainer.max_steps), ckpt_path=self.cfg.ckpt_path,
                             weights_only=False)  # fmt: skip
        except TrackingFailed as err:  # the method's result on this input: recorded, then reported
            write_tracking_failed(self.out, err, len(self.state.trajectory()), time.perf_counter() - self.started,
                                  self.provenance())  # fmt: skip
            raise
        if self.interrupt.exit_code is not None:
            raise SystemExit(self.interrupt.exit_code)

    def save_final(self) -> dict:
        """checkpoints/final.ckpt (a signal meanwhile waits for the write); -> metrics notes."""
        self.module.to(self.trainer.strategy.root_device)  # Lightning hands the module back on the CPU after fit
        final = self.out / "checkpoints" / "final.ckpt"
        with self.interrupt.in_phase("defer"):
            notes = save_final(self.trainer, final)
        self.final_checkpoint = notes["final_checkpoint"]
        if self.interrupt.exit_code is not None:
            print(f"segs: stopped after the final checkpoint; evaluate it with the same command plus  ckpt_path={final}",
                  file=sys.stderr)  # fmt: skip
            raise SystemExit(self.interrupt.exit_code)
        return notes

    def evaluate(self, notes: dict) -> dict:
        """Track the rest of the sequence, then the test views, ATE and metrics.json (a signal
        stops at once: no metrics.json)."""
        guard, trainer, record = self.guard, self.trainer, self.record
        watch = (lambda where: guard.check(trainer, where, save=False)) if guard is not None else None
        with self.interrupt.in_phase("now"):
            self.bridge.complete_sequence()
            timing = {"steps": trainer.global_step, "scheduled_steps": self.module.model.total_steps, "fit_s": record.fit_seconds(),
                      "wall_s": record.wall_seconds(), "sessions": record.sessions}  # fmt: skip
            evaluation = eval_config(self.cfg.eval)
            if not evaluation.enabled:
                metrics = write_not_evaluated(self.module, self.sequence, self.state, self.out, timing, notes, self.provenance())
                print(f"\nsegs: results in {self.out} (eval.enabled=false: no test view rendered)\n  {metrics['iterations']} "
                      f"iterations, {metrics['anchors']} anchors; metrics.json"
                      f"{', checkpoints/final.ckpt' if self.final_checkpoint else ''}")  # fmt: skip
                return metrics
            metrics = evaluate(self.module, self.sequence, self.state, evaluation, self.out, timing, notes, watch, self.provenance())
        _print_summary(self.out, metrics)
        return metrics

    def provenance(self) -> dict:
        return provenance(self.cfg, self.sequence.sensor, self.module.raster_backend, str(self.module.device))


def build(cfg: DictConfig, session_start: float | None = None) -> TrainingRun:
    """Check the config (and the checkpoint to resume), then instantiate sequence, run state
    (frame source and split), module, bridge, the interrupt handler and trainer.
    session_start: time.perf_counter() at the start of the run (default: now)."""
    started = time.perf_counter() if session_start is None else session_start
    validate(cfg)
    record = read_checkpoint(cfg.get("ckpt_path"))
    sequence = make_sequence(cfg.data)
    if len(sequence) == 0:
        raise DataError(f"data: the sequence at {cfg.data.get('root', '?')} has no frames")
    identity = fingerprint(cfg, sequence)
    if record is not None:
        check_resume(cfg.ckpt_path, record, identity)
    state = RunState(sequence, make_source(cfg, sequence), holdout_every=eval_config(cfg.eval).holdout_every)
    module = GaussianMapperModule(build_model(cfg.model), mapping_config(cfg.mapping), raster_config(cfg.raster), seed=cfg.seed)
    bridge: SlamBridge = instantiate(cfg.callbacks.slam_bridge)(run=state)
    # first: it takes the signals back from Lightning when training starts, before the bridge tracks
    interrupt = GracefulInterrupt(cfg.paths.output_dir)
    skip = {"slam_bridge"} | (set() if cfg.trainer.get("enable_progress_bar", True) else {"progress_bar"})  # bar off: no bar callback
    callbacks = [interrupt, bridge] + [instantiate(c) for k, c in cfg.callbacks.items() if k not in skip and c is not None]
    run_record = RunRecord(identity, started)
    callbacks.append(run_record)
    viewer = viewer_config(OmegaConf.to_container(cfg.viewer, resolve=True)) if "viewer" in cfg else None
    if viewer is not None:  # viewer=on: the map served to a browser while training (segs.viewer)
        from segs.viewer.live import LiveViewer

        callbacks.append(LiveViewer(viewer, sequence, align=cfg.eval.ate_align))
    loggers = [instantiate(c) for c in (cfg.get("logger") or {}).values() if c is not None]
    trainer: L.Trainer = instantiate(cfg.trainer, callbacks=callbacks, logger=loggers or False, default_root_dir=cfg.paths.output_dir,
                                     plugins=[DirectCheckpointIO()])
    guard = next((c for c in callbacks if isinstance(c, MemoryGuard)), None)
    return TrainingRun(cfg, Path(cfg.paths.output_dir), sequence, state, module, bridge, trainer, interrupt, run_record, guard,
                       started)  # fmt: skip


def save_final(trainer: L.Trainer, path: Path) -> dict:
    """Write the final checkpoint; a failure (disk full, read-only folder) is a warning and a
    note in metrics.json, never the loss of the run's results. Returns the metrics notes."""
    try:
        save_atomic(trainer, path)
    except (OSError, RuntimeError) as err:  # torch reports a failed write as RuntimeError
        why = f"{type(err).__name__}: {' '.join(str(err).split())}"[:300]
        log.warning("the final checkpoint %s could not be written (%s); the results are written without it", path, why)
        return {"final_checkpoint": None, "checkpoint_note": f"final checkpoint not written: {why}"}
    return {"final_checkpoint": str(path)}


def run(cfg: DictConfig) -> dict:
    """Train and evaluate; returns the metrics written to metrics.json.

    Order: fit, final checkpoint (a failed write does not stop the run), tracking of the frames
    not fed yet, evaluation, metrics.json last. Ctrl-C / SIGTERM at any point end with exit
    130 / 143 and one line (segs.callbacks.interrupt, the one handler, installed for the whole
    run), never with a metrics.json.
    """
    started = time.perf_counter()
    validate(cfg)  # before seeding: seed itself is checked
    L.seed_everything(cfg.seed, workers=True, verbose=False)
    training = build(cfg, started)
    try:
        with training.interrupt:
            return training.execute()
    except Interrupted as err:
        final = training.final_checkpoint
        where = f"the trained map is in {final}; evaluate it with the same command plus  ckpt_path={final}" if final \
            else "nothing was saved since the last checkpoint"  # fmt: skip
        print(f"\nsegs: stopped by {err}; no metrics.json written; {where}", file=sys.stderr)
        raise SystemExit(err.code) from None
    finally:
        training.state.source.close()


def _fmt(v, spec: str) -> str:
    return "n/a" if v is None else format(v, spec)


def _ate_line(m: dict) -> str:
    """'ATE RMSE 2.67 cm over 600/600 tracked frames', or n/a with the reason."""
    rmse, reason = m.get("ate_rmse_m"), (m.get("ate") or {}).get("reason")
    value = f"{rmse * 100:.2f} cm" if rmse is not None else f"n/a ({reason})" if reason else "n/a"
    return f"ATE RMSE {value} over {m['frames_tracked']}/{m['frames']} tracked frames"


def _of_scheduled(m: dict) -> str:
    """' of N' when the run stopped before its schedule's N steps (trainer.max_time, or a
    coarse-to-fine run shorter than mapping.min_schedule_steps), else ''."""
    n = m.get("scheduled_iterations")
    return f" of {n} scheduled" if n and m["iterations"] < n else ""


def _test_line(m: dict) -> str:
    """'  test views 15: PSNR 25.21 dB, SSIM 0.888, LPIPS n/a', or why there is none."""
    if not m["test_views"]:
        return f"  test views 0: {m['test_note']}\n"  # evaluate() writes it whenever there is no test view
    return (f"  test views {m['test_views']}: PSNR {_fmt(m['psnr'], '.2f')} dB, SSIM {_fmt(m['ssim'], '.3f')}, "
            f"LPIPS {_fmt(m['lpips'], '.3f')}\n")


def _print_summary(out: Path, m: dict) -> None:
    print(
        f"\nsegs: results in {out}\n"
        + _test_line(m)
        + (f"  {m['lossless_views']} of them also lossless: PSNR {m['psnr_lossless']:.2f} dB against the lossless frames "
           f"({m['psnr_jpeg_on_lossless_views']:.2f} dB against the JPEGs, which score {m['psnr_jpeg_vs_lossless']:.2f} dB)\n"
           if m.get("lossless_views") else "")
        + f"  {_ate_line(m)}\n"
        f"  {m['iterations']}{_of_scheduled(m)} iterations in {m['mapping_time_s']:.1f} s, {m['gaussians']} Gaussians, "
        f"{m['anchors']} anchors, {m['model_mb']:.2f} MB\n"
        + (f"  {m['frames_note']}\n" if m.get("frames_note") else "")
        + (f"  {m['checkpoint_note']}\n" if m.get("checkpoint_note") else "")
        + _ply_line(m)
        + "  " + ", ".join(_written(m))
    )


def _written(m: dict) -> list[str]:
    """The run folder's result files the summary lists: those this run wrote."""
    return (["metrics.json", "trajectory.txt"] + (["point_cloud.ply"] if m.get("ply_gaussians") is not None else [])
            + (["renders/"] if m.get("renders_saved") else []) + (["checkpoints/final.ckpt"] if m.get("final_checkpoint") else []))


def _ply_line(m: dict) -> str:
    """The written PLY's size and, for a fitted one, its test-view PSNR; '' without a PLY or its score."""
    if m.get("ply_psnr") is None:
        return ""
    return f"  point_cloud.ply: {m['ply_gaussians']} Gaussians, PSNR {m['ply_psnr']:.2f} dB on the test views as a 3D-GS viewer draws it\n"


@hydra.main(config_path="../../conf", config_name="train", version_base="1.3")
def main(cfg: DictConfig) -> float | None:
    torch.set_num_threads(max(torch.get_num_threads(), 1))
    with user_errors_exit():
        try:
            metrics = run(cfg)
        except TrackingFailed as err:
            if HydraConfig.get().mode != RunMode.MULTIRUN:
                raise
            # inside a sweep a tracking failure is a result (metrics.json says so), not a crash
            log.warning("tracking failed: %s", str(err).splitlines()[0])
            return None
    return metrics.get("psnr")


if __name__ == "__main__":
    main()
