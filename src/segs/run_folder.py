"""One run per folder: a run claims its folder before Hydra writes into it.

A run folder holds at most one run. Before Hydra saves `.hydra/` and opens the log, the
`ClaimRunFolder` Hydra callback (conf/hydra/default.yaml) takes an exclusive lock on
`<folder>/.segs.lock` (flock: the kernel drops it when the process ends, even on kill -9) and
refuses, with one line and exit 2, a folder that

- another live process holds (two runs started with the same `hydra.run.dir`), or
- already holds a result (`metrics.json`, `tracking.json`) or resumable work (a checkpoint in
  `checkpoints/`), unless this run resumes from a checkpoint inside that folder; a resumed run
  moves the old `metrics.json` aside (`metrics.previous.json`) so that an interrupted resume never
  leaves the old result under the new overrides.

A multirun claims its sweep folder the same way and refuses one that already holds a sweep
(`multirun.yaml`); its job folders are new sub-folders of the claimed sweep folder.
"""
from __future__ import annotations

import contextlib
import fcntl
import json
import os
import socket
import sys
from pathlib import Path

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from segs.errors import ConfigError

LOCK_NAME = ".segs.lock"
# what makes a folder hold a run that a new one must not overwrite (a failed start leaves only .hydra/)
RESULTS = ("metrics.json", "tracking.json")
_held: dict[Path, int] = {}  # folder -> open, locked descriptor (kept for the life of the process)


def _owner(lock: Path) -> str:
    try:
        text = lock.read_text().strip()
    except OSError:
        return "another process"
    return f"process {text}" if text else "another process"


def _work_in(folder: Path) -> str | None:
    """What finished or resumable work the folder holds, or None."""
    for name in RESULTS:
        if (folder / name).is_file():
            return f"a finished run ({name})"
    ckpts = sorted((folder / "checkpoints").glob("*.ckpt")) if (folder / "checkpoints").is_dir() else []
    if ckpts:
        return f"an unfinished run (checkpoint {ckpts[-1].name})"
    return None


def _inside(path: str | None, folder: Path) -> bool:
    if not path:
        return False
    return Path(path).expanduser().resolve().is_relative_to(folder.resolve())


def claim(folder: str | Path, resume_from: str | None = None, key: str = "hydra.run.dir", sweep: bool = False) -> Path:
    """Lock `folder` for this process (created if needed) or raise ConfigError saying why not.

    resume_from: the run's ckpt_path; a checkpoint inside `folder` allows reusing it.
    sweep: the folder of a multirun (refused when it holds multirun.yaml).
    """
    folder = Path(folder).expanduser().absolute()
    if folder in _held:
        return folder
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd = os.open(folder / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as err:
        raise ConfigError(f"{key}={folder}: cannot create the run folder ({err.strerror})") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        raise ConfigError(f"{key}={folder}: {_owner(folder / LOCK_NAME)} is running in this folder; "
                          "give this run another folder") from None  # fmt: skip
    work = "a sweep (multirun.yaml)" if sweep and (folder / "multirun.yaml").is_file() else _work_in(folder)
    if work is not None and not (not sweep and _inside(resume_from, folder)):
        os.close(fd)
        hint = "" if sweep or "checkpoint" not in work else f", or resume it with ckpt_path={folder}/checkpoints/last.ckpt"
        raise ConfigError(f"{key}={folder} already holds {work}; give this run another folder{hint}")
    if not sweep and (folder / "metrics.json").is_file():  # resuming in place: the old result is history
        os.replace(folder / "metrics.json", folder / "metrics.previous.json")
    os.ftruncate(fd, 0)
    os.write(fd, f"{os.getpid()} on {socket.gethostname()}\n".encode())
    _held[folder] = fd
    return folder


def release(folder: str | Path) -> None:
    """Unlock a folder claimed by this process (the end of the process does it too)."""
    fd = _held.pop(Path(folder).expanduser().absolute(), None)
    if fd is not None:
        os.close(fd)


def _select(config: DictConfig, key: str):
    from hydra.core.hydra_config import HydraConfig

    HydraConfig.instance().set_config(config)  # for ${hydra:...} inside the folder name
    return OmegaConf.select(config, key)


def _refuse(err: ConfigError) -> None:
    print(f"error: {err}", file=sys.stderr)
    raise SystemExit(2)


class ClaimRunFolder(Callback):
    """Hydra callback: claim hydra.run.dir (single run) or hydra.sweep.dir (multirun) at start."""

    def on_run_start(self, config: DictConfig, **kwargs) -> None:
        try:
            resume = OmegaConf.select(config, "ckpt_path", default=None, throw_on_resolution_failure=False)
            claim(_select(config, "hydra.run.dir"), None if resume is None else str(resume))
        except ConfigError as err:
            _refuse(err)

    def on_multirun_start(self, config: DictConfig, **kwargs) -> None:
        try:
            claim(_select(config, "hydra.sweep.dir"), key="hydra.sweep.dir", sweep=True)
        except ConfigError as err:
            _refuse(err)


def write_json_atomic(path: Path, data: dict) -> None:
    """A result file (metrics.json, tracking.json) written whole or not at all: a failed or
    interrupted write leaves neither a truncated file nor its .tmp."""
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.write_text(json.dumps(data, indent=2, sort_keys=False))
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        raise
