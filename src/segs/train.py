"""`python -m segs.train [+experiment=NAME] [+ablation=NAME] [key=value ...]`

Tracks the sequence with the configured frontend, trains the Gaussian map on its keyframes,
evaluates the test views and writes metrics.json, the trajectory, renders, a PLY and the final
checkpoint into the Hydra run folder.
"""
from __future__ import annotations

import logging
import time
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
import lightning as L
import torch
from lightning.pytorch.utilities.exceptions import SIGTERMException
from omegaconf import DictConfig, OmegaConf
from torch.utils.data import DataLoader, Dataset

from segs.callbacks import GracefulInterrupt, SlamBridge, save_atomic
from segs.config import instantiate, make_sequence, user_errors_exit, validate
from segs.errors import DataError, TrackingFailed
from segs.evaluation import evaluate, write_tracking_failed
from segs.modules.mapping import MappingModule

log = logging.getLogger("segs.train")


class StepDataset(Dataset):
    """One item per mapping step (the step index); views are sampled by the module itself."""

    def __init__(self, steps: int):
        self.steps = steps

    def __len__(self) -> int:
        return self.steps

    def __getitem__(self, i: int) -> int:
        return i


def build(cfg: DictConfig):
    """Instantiate sequence, frontend, module, bridge and trainer from the composed config."""
    validate(cfg)
    sequence = make_sequence(cfg.data)
    if len(sequence) == 0:
        raise DataError(f"data: the sequence at {cfg.data.get('root', '?')} has no frames")
    frontend = instantiate(cfg.slam)(camera=sequence.camera, sensor=sequence.sensor)
    module = MappingModule(instantiate(cfg.model), raster=OmegaConf.to_container(cfg.raster), seed=cfg.seed, **cfg.mapping)
    bridge: SlamBridge = instantiate(cfg.callbacks.slam_bridge)(sequence=sequence, frontend=frontend)
    callbacks = [bridge] + [instantiate(c) for k, c in cfg.callbacks.items() if k != "slam_bridge" and c is not None]
    loggers = [instantiate(c) for c in (cfg.get("logger") or {}).values() if c is not None]
    trainer: L.Trainer = instantiate(cfg.trainer, callbacks=callbacks, logger=loggers or False, default_root_dir=cfg.paths.output_dir)
    return sequence, frontend, module, bridge, trainer


def run(cfg: DictConfig) -> dict:
    """Train and evaluate; returns the metrics written to metrics.json."""
    t_start = time.perf_counter()
    L.seed_everything(cfg.seed, workers=True, verbose=False)
    out = Path(cfg.paths.output_dir)
    sequence, frontend, module, bridge, trainer = build(cfg)
    loader = DataLoader(StepDataset(cfg.trainer.max_steps), batch_size=None, shuffle=False)
    t_fit = time.perf_counter()
    stopper = next((c for c in trainer.callbacks if isinstance(c, GracefulInterrupt)), None)
    try:
        # our checkpoints hold numpy arrays (frontend map, RNG states): they are the user's own files
        trainer.fit(module, loader, ckpt_path=cfg.ckpt_path, weights_only=False)
    except TrackingFailed as err:  # the method's result on this input: recorded, then reported
        write_tracking_failed(out, err, len(frontend.trajectory()), time.perf_counter() - t_start)
        raise
    except SIGTERMException:  # Lightning's own SIGTERM handling stopped the loop (exit code 0 otherwise)
        if stopper is not None and stopper.checkpoint is None:
            stopper.stop(trainer)
        raise SystemExit(143) from None
    fit_s = time.perf_counter() - t_fit
    if stopper is not None and stopper.exit_code is not None:
        raise SystemExit(stopper.exit_code)
    if trainer.interrupted:  # Lightning caught a KeyboardInterrupt itself (no handler installed)
        raise SystemExit(130)
    bridge.complete_sequence()
    module.to(trainer.strategy.root_device)  # Lightning hands the module back on the CPU after fit
    save_atomic(trainer, out / "checkpoints" / "final.ckpt")
    if not cfg.eval.enabled:
        return {}
    timing = {"steps": trainer.global_step, "fit_s": fit_s, "wall_s": time.perf_counter() - t_start}
    metrics = evaluate(module, sequence, bridge, cfg.eval, out, timing)
    metrics["wall_time_s"] = time.perf_counter() - t_start
    _print_summary(out, metrics)
    return metrics


def _fmt(v, spec: str) -> str:
    return "n/a" if v is None else format(v, spec)


def _print_summary(out: Path, m: dict) -> None:
    print(
        f"\nsegs: results in {out}\n"
        f"  test views {m['test_views']}: PSNR {_fmt(m['psnr'], '.2f')} dB, SSIM {_fmt(m['ssim'], '.3f')}, "
        f"LPIPS {_fmt(m['lpips'], '.3f')}\n"
        f"  ATE RMSE {_fmt(m['ate_rmse_m'] and m['ate_rmse_m'] * 100, '.2f')} cm over {m['frames_tracked']}/{m['frames']} tracked frames\n"
        f"  {m['iterations']} iterations in {m['mapping_time_s']:.1f} s, {m['gaussians']} Gaussians, "
        f"{m['anchors']} anchors, {m['model_mb']:.2f} MB\n"
        f"  metrics.json, trajectory.txt, point_cloud.ply, renders/, checkpoints/final.ckpt"
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
