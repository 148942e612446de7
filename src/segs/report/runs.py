"""Finding and reading Hydra run folders: metrics.json, .hydra/{overrides,config,hydra}.yaml.

A run folder is any folder holding ``.hydra/overrides.yaml``; a multirun folder holds numbered
job folders and ``multirun.yaml``. A run without metrics.json crashed or has not finished; it is
kept as such (never given numbers). For a multirun with the basic sweeper the expected jobs are
expanded from multirun.yaml with Hydra's own override parser, so that jobs that never started
(a sweep killed half-way) are reported too.
"""
from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from segs.errors import UserInputError

log = logging.getLogger(__name__)

FAILURE_FILE = "job_failed.txt"  # written by segs.report.hydra_callbacks.RecordFailure
# override keys that choose the method / ablation (shown as the series, not as a variant)
METHOD_KEYS = ("sweep/method", "ablation", "model")


@dataclass
class Run:
    """One job: where it is, how it was configured, what it measured (None: no metrics.json)."""

    path: Path
    overrides: list[str]
    choices: dict = field(default_factory=dict)
    config: DictConfig | None = None
    metrics: dict | None = None
    failure: str | None = None  # first line of job_failed.txt
    started: bool = True  # False: expected from multirun.yaml, no job folder
    superseded: bool = False  # no metrics, no error, and a rerun with the same overrides exists

    @property
    def status(self) -> str:
        """finished | not_evaluated (trained with eval.enabled=false: no image / ATE metric) |
        tracking_failed (metrics.json says the frontend tracked nothing mappable) |
        failed (error recorded) | no metrics (crashed or still running) | not started."""
        if not self.started:
            return "not started"
        if self.superseded:
            return "superseded by a rerun"
        if self.metrics is not None:
            return str(self.metrics.get("status", "finished"))
        return "failed" if self.failure else "no metrics"

    @property
    def crashed(self) -> bool:
        """A started job without metrics.json (not counting one that a rerun replaced)."""
        return self.started and self.metrics is None and not self.superseded

    @property
    def method(self) -> str:
        """Method / ablation name: sweep/method or ablation chosen, else the model (segs, plain_3dgs)."""
        if not self.choices:  # a job that never started: what its overrides say, if anything
            named = {o.split("=", 1)[0].lstrip("+"): o.split("=", 1)[1] for o in self.overrides if "=" in o}
            return next((named[k] for k in METHOD_KEYS if k in named), "?")
        for key in ("sweep/method", "ablation"):
            if self.choices.get(key):
                return str(self.choices[key])
        model = self.choices.get("model") or "segs"
        return str(model)

    @property
    def experiment(self) -> str:
        return str(self.choices.get("experiment") or "default")

    def get(self, key: str, default=None):
        """A config value by dotted key (unresolved interpolations are returned as None)."""
        if self.config is None:
            return default
        try:
            value = OmegaConf.select(self.config, key, default=default, throw_on_resolution_failure=False)
        except Exception:  # an interpolation into the hydra node, which the saved config lacks
            return default
        return OmegaConf.to_container(value, resolve=False) if isinstance(value, DictConfig) else value

    @property
    def stress(self) -> tuple[str | None, float]:
        """(kind, level) of data.stress; (None, 0.0) without stress (the unstressed baseline)."""
        node = self.get("data.stress")
        if not node:
            return None, 0.0
        return node.get("kind"), float(node.get("level", 0.0))

    def metric(self, key: str):
        """A finite number from metrics.json, else None."""
        value = (self.metrics or {}).get(key)
        if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
            return value
        return None


def _load_yaml(path: Path):
    return OmegaConf.load(path) if path.is_file() else None


def _first_line(path: Path) -> str | None:
    if not path.is_file():
        return None
    lines = [ln.strip() for ln in path.read_text(errors="replace").splitlines() if ln.strip()]
    return lines[0] if lines else "failed"


def load_run(path: Path) -> Run:
    """Read one run folder (which holds .hydra/overrides.yaml)."""
    hydra_dir = path / ".hydra"
    overrides = OmegaConf.to_container(_load_yaml(hydra_dir / "overrides.yaml") or OmegaConf.create([]))
    hydra_cfg = _load_yaml(hydra_dir / "hydra.yaml")
    choices = {}
    if hydra_cfg is not None:
        node = OmegaConf.select(hydra_cfg, "hydra.runtime.choices", default=None)
        choices = {k: v for k, v in (OmegaConf.to_container(node) if node is not None else {}).items() if v is not None}
    metrics = None
    if (path / "metrics.json").is_file():
        try:
            metrics = json.loads((path / "metrics.json").read_text())
        except json.JSONDecodeError:
            log.warning("%s: metrics.json is not valid JSON; counted as a run without metrics", path)
    return Run(path=path, overrides=[str(o) for o in overrides], choices=choices,
               config=_load_yaml(hydra_dir / "config.yaml"), metrics=metrics,
               failure=_first_line(path / FAILURE_FILE))  # fmt: skip


def find_run_dirs(root: Path) -> list[Path]:
    """Run folders at or below root, in natural order (job 2 before job 10)."""
    found = [p.parent.parent for p in root.rglob(".hydra/overrides.yaml")]
    if (root / ".hydra" / "overrides.yaml").is_file() and root not in found:
        found.append(root)

    def natural(p: Path):
        return [(0, int(part), "") if part.isdigit() else (1, 0, part) for part in p.relative_to(root).parts]

    return sorted(set(found), key=natural)


def expected_jobs(multirun_dir: Path) -> list[list[str]] | None:
    """Override lists of every job of a basic-sweeper multirun, from its multirun.yaml.

    None when that cannot be known (another sweeper, no multirun.yaml, unparsable overrides).
    """
    cfg = _load_yaml(multirun_dir / "multirun.yaml")
    if cfg is None or "BasicSweeper" not in str(OmegaConf.select(cfg, "hydra.sweeper._target_", default="")):
        return None
    params = OmegaConf.select(cfg, "hydra.sweeper.params", default=None) or {}
    args = [f"{k}={v}" for k, v in params.items()]
    args += [str(o) for o in OmegaConf.select(cfg, "hydra.overrides.task", default=[]) or []]
    try:
        return _expand(args)
    except Exception as err:  # noqa: BLE001 - any parse problem only means "unknown"
        log.warning("%s: cannot expand the sweep (%s); jobs that never started are not counted", multirun_dir, err)
        return None


def _expand(args: list[str]) -> list[list[str]]:
    """Hydra's BasicSweeper expansion of override strings (glob resolved on this repo's conf/)."""
    from hydra import initialize_config_dir
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.override_parser.overrides_parser import OverridesParser

    from segs.config import CONF_DIR

    loader = None
    if any("glob(" in a for a in args):
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            loader = GlobalHydra.instance().config_loader()
    parser = OverridesParser.create(config_loader=loader)
    batches = BasicSweeper.split_arguments(parser.parse_overrides(args), None)
    return [list(job) for batch in batches for job in batch]


def _same(a: list[str], b: list[str]) -> bool:
    return sorted(a) == sorted(b)


def collect(dirs: list[str | Path]) -> list[Run]:
    """Every run under the given run / multirun folders, plus expected jobs that never started.

    A job expected by one multirun but found in another given folder (a rerun of the jobs a
    killed sweep left) counts as started; a job without metrics.json and without an error of its
    own whose overrides another given run repeats (with a result or an error) is "superseded".
    """
    dirs = [Path(d) for d in dirs]
    for d in dirs:
        if not d.is_dir():
            raise UserInputError(f"segs.report: {d} is not a folder")
    runs = [load_run(p) for d in dirs for p in find_run_dirs(d)]
    for r in runs:  # a job killed with its sweep (no error of its own) and run again elsewhere
        r.superseded = r.metrics is None and not r.failure and any(
            o is not r and _same(o.overrides, r.overrides) and (o.metrics is not None or o.failure) for o in runs)
    for d in dirs:
        for job in expected_jobs(d) or []:
            if not any(_same(job, r.overrides) for r in runs):
                runs.append(Run(path=d, overrides=job, started=False))
    if not runs:
        raise UserInputError(f"segs.report: no run folders (.hydra/overrides.yaml) under {', '.join(map(str, dirs))}")
    return runs


def common_overrides(runs: list[Run]) -> list[str]:
    """Overrides shared by every run, in the first run's order."""
    if not runs:
        return []
    shared = set(runs[0].overrides).intersection(*(set(r.overrides) for r in runs[1:]))
    return [o for o in runs[0].overrides if o in shared]


def variant(run: Run, common: list[str], skip: tuple[str, ...] = ()) -> str:
    """The run's own overrides (not shared by all runs, not method keys or `skip` keys), shortened."""
    parts = []
    for o in run.overrides:
        key = o.split("=", 1)[0].lstrip("+~")
        if o in common or key in METHOD_KEYS or key in skip:
            continue
        if key.startswith("sweep/"):
            o = o.split("=", 1)[1]  # a sweep variant file: its name says it all
        parts.append(o.lstrip("+").replace("trainer.", "").replace("model.", "").replace("data.", ""))
    return " ".join(parts)
