"""What a checkpoint records about its run, so that a resumed run is the same run.

`RunRecord` (added by segs.train to every trainer) writes into each checkpoint

- the run's fingerprint: sequence, sensor, camera, stress, frontend, model and its architecture,
  hold-out rule. Resuming with any of them changed is refused before any work, naming the key;
- the time spent so far (wall clock, fit) and every iteration time, so that the metrics of a
  resumed run cover the whole run (times summed over sessions), not its last session.

:func:`read_checkpoint` checks a `ckpt_path` before anything runs (missing, a folder, truncated).
"""
from __future__ import annotations

import time
from pathlib import Path

import lightning as L
from omegaconf import DictConfig, OmegaConf

from segs.errors import ConfigError

KEY = "segs_run"
# model keys that change the parameters' shapes or meaning (the rest, e.g. learning rates, may change)
ARCHITECTURE = ("k", "feature_dim", "hidden", "use_distance", "appearance.kind", "appearance.dim", "sh_degree")


def fingerprint(cfg: DictConfig, sequence) -> dict:
    """The identity of a run's data, camera and model (values are plain strings / numbers)."""
    cam = sequence.camera
    arch = {k: OmegaConf.select(cfg.model, k, default=None) for k in ARCHITECTURE}
    stress = OmegaConf.select(cfg, "data.stress", default=None)
    return {
        "sequence": f"{getattr(sequence, 'name', '?')} ({len(sequence)} frames)",
        "sensor": str(sequence.sensor),
        "camera": f"{cam.width}x{cam.height} fx={cam.fx:.6g} fy={cam.fy:.6g} cx={cam.cx:.6g} cy={cam.cy:.6g} "
                  f"baseline={cam.baseline}",
        "data.stress": None if not stress else str(OmegaConf.to_container(stress, resolve=True)),
        "slam": str(cfg.slam._target_),
        "model": str(cfg.model._target_),
        "model architecture": " ".join(f"{k}={v}" for k, v in arch.items() if v is not None),
        "eval.holdout_every": OmegaConf.select(cfg, "eval.holdout_every", default=None),
    }


def read_checkpoint(path: str | None) -> dict | None:
    """The RunRecord of a checkpoint file ({} for one written before RunRecord existed), None
    without ckpt_path; ConfigError when the file is missing, a folder or not a readable checkpoint."""
    if path is None:
        return None
    import torch

    p = Path(str(path)).expanduser()
    if p.is_dir():
        raise ConfigError(f"ckpt_path={path} is a folder: expected a checkpoint file (e.g. {p / 'checkpoints' / 'last.ckpt'})")
    if not p.is_file():
        raise ConfigError(f"ckpt_path={path}: checkpoint file not found")
    try:  # mmap: tensors stay on disk; a truncated file has no zip directory and fails here
        ckpt = torch.load(p, map_location="cpu", weights_only=False, mmap=True)
    except Exception as err:  # noqa: BLE001 - any reader error means the same to the user
        raise ConfigError(f"ckpt_path={path}: not a readable checkpoint (truncated or corrupt?): {type(err).__name__}") from None
    if not isinstance(ckpt, dict) or "state_dict" not in ckpt or "global_step" not in ckpt:
        raise ConfigError(f"ckpt_path={path}: not a segs checkpoint (no state_dict / global_step)")
    return dict(ckpt.get(KEY) or {})


def check_resume(path: str, record: dict, current: dict) -> None:
    """ConfigError naming the first fingerprint entry that differs between checkpoint and run."""
    # checkpoints written before the config group camera was renamed sensor
    saved = {("sensor" if k == "camera.sensor" else k): v for k, v in (record.get("fingerprint") or {}).items()}
    for key, value in current.items():
        if key in saved and saved[key] != value:
            raise ConfigError(f"ckpt_path={path} was written by a run with {key} {saved[key]!r}, this run has "
                              f"{value!r}; resume with the same data, camera, frontend and model")  # fmt: skip


class RunRecord(L.Callback):
    """Fingerprint and accumulated times in every checkpoint (see the module doc).

    session_start: time.perf_counter() when this session (process) started the run.
    """

    def __init__(self, fingerprint: dict, session_start: float | None = None):
        self.fingerprint = fingerprint
        self.session_start = time.perf_counter() if session_start is None else session_start
        self.before = {"wall_s": 0.0, "fit_s": 0.0, "sessions": 0}  # sessions before this one
        self._fit_start: float | None = None
        self._fit_s: float | None = None  # this session's fit time, once fit has ended

    def fit_seconds(self) -> float:
        """Fit time of every session so far (this one up to now, or to its end)."""
        if self._fit_s is not None:
            return self.before["fit_s"] + self._fit_s
        now = 0.0 if self._fit_start is None else time.perf_counter() - self._fit_start
        return self.before["fit_s"] + now

    def wall_seconds(self) -> float:
        """Wall time of every session so far."""
        return self.before["wall_s"] + time.perf_counter() - self.session_start

    @property
    def sessions(self) -> int:
        return self.before["sessions"] + 1

    def on_fit_start(self, trainer, pl_module) -> None:
        self._fit_start, self._fit_s = time.perf_counter(), None

    def on_fit_end(self, trainer, pl_module) -> None:
        self._fit_s = time.perf_counter() - self._fit_start

    def on_save_checkpoint(self, trainer, pl_module, checkpoint: dict) -> None:
        checkpoint[KEY] = {
            "fingerprint": self.fingerprint,
            "wall_s": self.wall_seconds(),
            "fit_s": self.fit_seconds(),
            "sessions": self.sessions,
            "iteration_ms": list(pl_module.iteration_ms),
        }

    def on_load_checkpoint(self, trainer, pl_module, checkpoint: dict) -> None:
        record = checkpoint.get(KEY)
        if not record:  # written before RunRecord: the times of this session only
            return
        self.before = {"wall_s": float(record["wall_s"]), "fit_s": float(record["fit_s"]), "sessions": int(record["sessions"])}
        pl_module.iteration_ms = list(record["iteration_ms"])
