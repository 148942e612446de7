"""`python -m segs.train [+experiment=NAME] [+ablation=NAME] [key=value ...]`

Tracks the sequence with the configured frontend, trains the Gaussian map on its keyframes,
evaluates the test views and writes metrics.json, the trajectory, renders, a PLY and the final
checkpoint into the Hydra run folder.
"""
from __future__ import annotations

if __name__ == "__main__":  # the program: process settings before torch loads (docs/decisions/028-process-settings.md)
    from segs import process_settings

    process_settings.apply()

import contextlib
import logging
import sys
import time
from pathlib import Path

import hydra
import lightning as L
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from lightning.pytorch.utilities.exceptions import SIGTERMException
from omegaconf import DictConfig, OmegaConf
from torch.utils.data import DataLoader, Dataset

from segs.callbacks import GracefulInterrupt, MemoryGuard, SlamBridge, save_atomic
from segs.callbacks.checkpoint import DirectCheckpointIO
from segs.callbacks.interrupt import Interrupted
from segs.callbacks.run_record import RunRecord, check_resume, fingerprint, read_checkpoint
from segs.config import instantiate, make_frontend, make_sequence, user_errors_exit, validate
from segs.errors import DataError, TrackingFailed
from segs.eval_config import eval_config
from segs.evaluation import evaluate, write_not_evaluated, write_tracking_failed
from segs.modules.config import build_model, mapping_config, raster_config
from segs.modules.gaussian_mapper import GaussianMapperModule
from segs.provenance import provenance
from segs.slam.runtime.process import FrontendProcess
from segs.viewer.config import viewer_config

log = logging.getLogger("segs.train")


class StepDataset(Dataset):
    """One item per mapping step (the step index); views are sampled by the module itself."""

    def __init__(self, steps: int):
        self.steps = steps

    def __len__(self) -> int:
        return self.steps

    def __getitem__(self, i: int) -> int:
        return i


def build(cfg: DictConfig, session_start: float | None = None):
    """Check the config (and the checkpoint to resume), then instantiate sequence, frontend,
    module, bridge and trainer. session_start: time.perf_counter() at the start of the run."""
    validate(cfg)
    record = read_checkpoint(cfg.get("ckpt_path"))
    sequence = make_sequence(cfg.data)
    if len(sequence) == 0:
        raise DataError(f"data: the sequence at {cfg.data.get('root', '?')} has no frames")
    identity = fingerprint(cfg, sequence)
    if record is not None:
        check_resume(cfg.ckpt_path, record, identity)
    frontend = make_frontend(cfg, sequence)
    module = GaussianMapperModule(build_model(cfg.model), mapping_config(cfg.mapping), raster_config(cfg.raster), seed=cfg.seed)
    bridge: SlamBridge = instantiate(cfg.callbacks.slam_bridge)(sequence=sequence, frontend=frontend)
    callbacks = [bridge] + [instantiate(c) for k, c in cfg.callbacks.items() if k != "slam_bridge" and c is not None]
    callbacks.append(RunRecord(identity, session_start))
    viewer = viewer_config(OmegaConf.to_container(cfg.viewer, resolve=True)) if "viewer" in cfg else None
    if viewer is not None:  # viewer=on: the map served to a browser while training (segs.viewer)
        from segs.viewer.live import LiveViewer

        callbacks.append(LiveViewer(viewer, sequence, align=cfg.eval.ate_align))
    loggers = [instantiate(c) for c in (cfg.get("logger") or {}).values() if c is not None]
    trainer: L.Trainer = instantiate(cfg.trainer, callbacks=callbacks, logger=loggers or False, default_root_dir=cfg.paths.output_dir,
                                     plugins=[DirectCheckpointIO()])  # fmt: skip
    return sequence, frontend, module, bridge, trainer


def _find(trainer: L.Trainer, kind: type):
    return next((c for c in trainer.callbacks if isinstance(c, kind)), None)


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
    130 / 143 and one line (segs.callbacks.interrupt), never with a metrics.json.
    """
    t_start = time.perf_counter()
    validate(cfg)  # before seeding: seed itself is checked
    L.seed_everything(cfg.seed, workers=True, verbose=False)
    out = Path(cfg.paths.output_dir)
    sequence, frontend, module, bridge, trainer = build(cfg, t_start)
    # the DataLoader draws its base seed from this generator, not from torch's global RNG, which a
    # resumed run restores from its checkpoint (one draw there made resumed runs diverge)
    loader = DataLoader(StepDataset(cfg.trainer.max_steps), batch_size=None, shuffle=False,
                        generator=torch.Generator().manual_seed(cfg.seed))  # fmt: skip
    stopper = _find(trainer, GracefulInterrupt) or contextlib.nullcontext()
    saved: dict = {}  # "final": the final checkpoint once this session has written it
    try:
        with stopper:
            return _run(cfg, out, sequence, frontend, module, bridge, trainer, loader, stopper, t_start, saved)
    except Interrupted as err:
        final = saved.get("final")
        where = f"the trained map is in {final}; evaluate it with the same command plus  ckpt_path={final}" if final \
            else "nothing was saved since the last checkpoint"  # fmt: skip
        print(f"\nsegs: stopped by {err}; no metrics.json written; {where}", file=sys.stderr)
        raise SystemExit(err.code) from None
    finally:
        if isinstance(frontend, FrontendProcess):
            frontend.close()


def _run(cfg, out, sequence, frontend, module, bridge, trainer, loader, stopper, t_start, saved: dict) -> dict:
    record, guard = _find(trainer, RunRecord), _find(trainer, MemoryGuard)
    phase = getattr(stopper, "in_phase", lambda _: contextlib.nullcontext())
    try:
        # our checkpoints hold numpy arrays (frontend map, RNG states): they are the user's own files
        trainer.fit(module, loader, ckpt_path=cfg.ckpt_path, weights_only=False)
    except TrackingFailed as err:  # the method's result on this input: recorded, then reported
        write_tracking_failed(out, err, len(frontend.trajectory()), time.perf_counter() - t_start, _provenance(cfg, sequence, module))
        raise
    except SIGTERMException:  # Lightning's own SIGTERM handling stopped the loop (exit code 0 otherwise)
        if isinstance(stopper, GracefulInterrupt) and stopper.checkpoint is None:
            stopper.stop(trainer)
        raise SystemExit(143) from None
    if getattr(stopper, "exit_code", None) is not None:
        raise SystemExit(stopper.exit_code)
    if trainer.interrupted:  # Lightning caught a KeyboardInterrupt itself (no handler installed)
        raise SystemExit(130)
    module.to(trainer.strategy.root_device)  # Lightning hands the module back on the CPU after fit
    final = out / "checkpoints" / "final.ckpt"
    with phase("defer"):
        notes = save_final(trainer, final)
    saved["final"] = notes["final_checkpoint"]
    if getattr(stopper, "exit_code", None) is not None:
        print(f"segs: stopped after the final checkpoint; evaluate it with the same command plus  ckpt_path={final}", file=sys.stderr)
        raise SystemExit(stopper.exit_code)
    watch = (lambda where: guard.check(trainer, where, save=False)) if guard is not None else None
    with phase("now"):
        bridge.complete_sequence()
        timing = {"steps": trainer.global_step, "fit_s": record.fit_seconds(), "wall_s": record.wall_seconds(), "sessions": record.sessions}
        made = _provenance(cfg, sequence, module)
        evaluation = eval_config(cfg.eval)
        if not evaluation.enabled:
            metrics = write_not_evaluated(module, sequence, bridge, out, timing, notes, made)
            print(f"\nsegs: results in {out} (eval.enabled=false: no test view rendered)\n  {metrics['iterations']} iterations, "
                  f"{metrics['anchors']} anchors; metrics.json{', checkpoints/final.ckpt' if saved['final'] else ''}")  # fmt: skip
            return metrics
        metrics = evaluate(module, sequence, bridge, evaluation, out, timing, notes, watch, made)
    _print_summary(out, metrics)
    return metrics


def _provenance(cfg: DictConfig, sequence, module: GaussianMapperModule) -> dict:
    return provenance(cfg, sequence.sensor, module.raster_backend, str(module.device))


def _fmt(v, spec: str) -> str:
    return "n/a" if v is None else format(v, spec)


def _ate_line(m: dict) -> str:
    """'ATE RMSE 2.67 cm over 600/600 tracked frames', or n/a with the reason."""
    rmse, reason = m.get("ate_rmse_m"), (m.get("ate") or {}).get("reason")
    value = f"{rmse * 100:.2f} cm" if rmse is not None else f"n/a ({reason})" if reason else "n/a"
    return f"ATE RMSE {value} over {m['frames_tracked']}/{m['frames']} tracked frames"


def _print_summary(out: Path, m: dict) -> None:
    print(
        f"\nsegs: results in {out}\n"
        f"  test views {m['test_views']}: PSNR {_fmt(m['psnr'], '.2f')} dB, SSIM {_fmt(m['ssim'], '.3f')}, "
        f"LPIPS {_fmt(m['lpips'], '.3f')}\n"
        + (f"  {m['lossless_views']} of them also lossless: PSNR {m['psnr_lossless']:.2f} dB against the lossless frames "
           f"({m['psnr_jpeg_on_lossless_views']:.2f} dB against the JPEGs, which score {m['psnr_jpeg_vs_lossless']:.2f} dB)\n"
           if m.get("lossless_views") else "")
        + f"  {_ate_line(m)}\n"
        f"  {m['iterations']} iterations in {m['mapping_time_s']:.1f} s, {m['gaussians']} Gaussians, "
        f"{m['anchors']} anchors, {m['model_mb']:.2f} MB\n"
        + (f"  {m['frames_note']}\n" if m.get("frames_note") else "")
        + (f"  {m['checkpoint_note']}\n" if m.get("checkpoint_note") else "")
        + f"  metrics.json, trajectory.txt, point_cloud.ply, renders/{', checkpoints/final.ckpt' if m.get('final_checkpoint') else ''}"
    )


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
