"""What every bench script shares: the process settings, where the shared real data is, the
record of the machine and the code, a timer, the JSON writer, and the bare training run of the
two training benches.

A script imports it first (`python bench/NAME.py` puts bench/ on sys.path) and calls
`apply_process_settings()` before the imports that load torch (docs/decisions/028-process-settings.md).
The shared data is read where it lies (non-commercial licences: never copied into the
repository): `$SEGS_SHARED_DATA`, else `shared/data` beside the checkout. segs is imported in the
functions that use it: bench/side_by_side.py runs its workers on an older segs as well.
"""
from __future__ import annotations

import datetime
import os
import statistics
import sys
import time
from pathlib import Path
from typing import Any, Callable

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("SEGS_SHARED_DATA") or ROOT.parent / "shared" / "data")
SEVEN_SCENES = SHARED_DATA / "7scenes_redkitchen_0000_0599"  # 600 real 7-Scenes redkitchen frames
OUTPUTS = ROOT / "outputs" / "bench"

# a bare segs.train run: no loggers, bars, image logging, checkpoints or signal handlers
QUIET = ["logger=none", "~callbacks.progress_bar", "~callbacks.image_logger", "~callbacks.periodic_checkpoint",
         "callbacks.slam_bridge.progress=false", "trainer.enable_progress_bar=false", "eval.progress=false"]  # fmt: skip
FEED_ALL = "callbacks.slam_bridge.min_initial_keyframes=1000000000"  # every frame is fed before the first step


def apply_process_settings() -> None:
    """segs's process settings (OMP_WAIT_POLICY=PASSIVE unless set, freed memory kept), as the
    programs `python -m segs.*` apply them; call before torch loads."""
    try:
        from segs import process_settings
    except ImportError:  # a segs older than process_settings applied them when imported
        import segs  # noqa: F401
        return
    process_settings.apply()


def load_average() -> list[float]:
    """The 1, 5 and 15 minute load averages (the host is shared: record them with timings)."""
    return [round(x, 2) for x in os.getloadavg()]


def record() -> dict:
    """The machine and the code of a measurement: {"machine": provenance.machine() (CPU, cores,
    OS, Python) with torch's threads when torch is loaded and the load average, "code": the segs
    package that runs (its folder) and provenance.git_state() of its checkout (commit, dirty),
    "time": local ISO time}."""
    import segs
    from segs.provenance import git_state, machine

    torch = sys.modules.get("torch")
    threads = torch.get_num_threads() if torch is not None else None
    return {"machine": {**machine(), "torch_threads": threads, "load_avg": load_average()},
            "code": {"source": str(Path(segs.__file__).resolve().parent), **git_state()},
            "time": datetime.datetime.now().isoformat(timespec="seconds")}  # fmt: skip


def short_commit(root: Path = ROOT) -> str:
    """The commit of the checkout at root, short, with "+changes" when tracked files differ; "?"
    outside a git checkout."""
    from segs.provenance import git_state

    state = git_state(Path(root))
    if state["commit"] is None:
        return "?"
    return state["commit"][:7] + ("+changes" if state["dirty"] else "")


def median_seconds(fn: Callable[[], Any], repeats: int, *, warmup: int = 0, setup: Callable[[], Any] | None = None) -> float:
    """Median wall-clock seconds of fn() over `repeats` calls, after `warmup` untimed calls;
    setup() runs untimed before each call (e.g. to restore what fn changes)."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(max(repeats, 1)):
        if setup is not None:
            setup()
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def medians(rows: list[dict]) -> dict:
    """Per key, the median over rows where the first row's value is a float (a measurement);
    other values (counts, names, None) are the first row's. rows: one dict per repeat, same keys."""
    return {k: statistics.median([r[k] for r in rows]) if isinstance(v, float) else v for k, v in rows[0].items()}


def write_json(path: str | Path, data: dict | list) -> Path:
    """The result JSON, its folder created, written whole or not at all (segs.run_folder)."""
    from segs.run_folder import write_json_atomic

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomic(path, data)
    return path


def build_training(overrides: list[str], max_steps: int, out: Path, callbacks: list):
    """segs.train.build of the composed run with QUIET, FEED_ALL and trainer.max_steps, seeded as
    segs.train seeds it, `callbacks` added to its trainer; -> (cfg, sequence, module, bridge, trainer)."""
    import lightning as L

    from segs.config import compose
    from segs.train import build

    cfg = compose(overrides + QUIET + [FEED_ALL, f"trainer.max_steps={max_steps}"], output_dir=str(out))
    L.seed_everything(cfg.seed, workers=True, verbose=False)
    training = build(cfg, time.perf_counter())
    training.trainer.callbacks.extend(callbacks)
    return cfg, training.sequence, training.module, training.bridge, training.trainer


def fit(cfg, module, trainer) -> None:
    """trainer.fit over segs.train's step indices (segs.train.step_batches)."""
    from segs.train import step_batches

    trainer.fit(module, step_batches(cfg.trainer.max_steps), weights_only=False)
