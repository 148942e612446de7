"""Hydra glue shared by the entry points and the tests: config folder, resolvers, validation."""
from __future__ import annotations

import contextlib
import inspect
import logging
import math
import re
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

from omegaconf import DictConfig, OmegaConf

from segs import schema
from segs.errors import ConfigError, UserInputError
from segs.slam.config import slam_config

log = logging.getLogger("segs")

REPO_ROOT = Path(__file__).resolve().parents[2]
CONF_DIR = REPO_ROOT / "conf"

if not OmegaConf.has_resolver("segs_root"):
    OmegaConf.register_new_resolver("segs_root", lambda: str(REPO_ROOT))


def _integer(value, key: str) -> int:
    """value as an int; ValueError naming `key` when it is not a whole number (a resolver's input)."""
    try:
        number = None if isinstance(value, bool) else float(value)
    except (TypeError, ValueError):
        number = None
    if number is None or not number.is_integer():
        raise ValueError(f"{key}={value!r} is not an integer")
    return int(number)


def schedule_steps(max_steps: int, num_downscales: int, min_steps: int) -> int:
    """The schedules' length (model.total_steps): the run's trainer.max_steps, or
    mapping.min_schedule_steps when the run is coarse-to-fine (num_downscales > 0) and shorter."""
    steps, min_steps = _integer(max_steps, "trainer.max_steps"), _integer(min_steps, "mapping.min_schedule_steps")
    return max(steps, min_steps) if _integer(num_downscales, "mapping.num_downscales") > 0 else steps


if not OmegaConf.has_resolver("segs_schedule"):
    OmegaConf.register_new_resolver("segs_schedule", schedule_steps)


def compose(overrides: list[str] | None = None, config_name: str = "train", output_dir: str | None = None) -> DictConfig:
    """Compose the config as `python -m segs.train OVERRIDES` would (for tests and notebooks).

    output_dir replaces the Hydra run folder (which only exists inside @hydra.main).
    """
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = hydra_compose(config_name=config_name, overrides=list(overrides or []), return_hydra_config=True)
    if output_dir is not None:
        cfg.hydra.runtime.output_dir = str(output_dir)
    from hydra.core.hydra_config import HydraConfig

    HydraConfig.instance().set_config(cfg)
    return cfg


def model_node(name: str = "segs", total_steps: int = 30000, **overrides) -> DictConfig:
    """conf/model/<name>.yaml with total_steps and nested overrides merged, resolved (tests,
    notebooks): segs.modules.config.build_model(model_node("segs", k=4)) is that model."""
    root = OmegaConf.create({"trainer": {"max_steps": total_steps}, "model": OmegaConf.load(CONF_DIR / "model" / f"{name}.yaml")})
    model = OmegaConf.merge(root.model, overrides)
    return OmegaConf.create(OmegaConf.to_container(OmegaConf.merge(root, {"model": model}).model, resolve=True))


def slam_frontend(camera, sensor: str, name: str = "orb", **overrides):
    """The frontend of conf/slam/<name>.yaml for `camera` / `sensor`, with nested overrides
    merged (tests, notebooks, benches): slam_frontend(cam, "rgbd", local_mapping={"ba_window": 5},
    threaded=True). The YAML holds every default; the frontend's own builder checks the keys."""
    node = OmegaConf.merge(OmegaConf.load(CONF_DIR / "slam" / f"{name}.yaml"), overrides)
    slam_config(node)
    return instantiate(node)(camera=camera, sensor=sensor)


ALIGNMENTS = ("se3", "sim3", "none")


def _number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


# (key, predicate, expectation) checked before anything runs; keys absent from a config are skipped
# how the frontend runs beside mapping (segs.pipeline's frame sources; conf/train.yaml slam_mode)
SLAM_MODES = ("interleaved", "process", "live")

_CHECKS: list[tuple[str, Callable[[object], bool], str]] = [
    ("trainer.max_steps", lambda v: isinstance(v, int) and v > 0, "an integer > 0"),
    ("trainer.max_time", lambda v: v is None or bool(re.fullmatch(r"\d+:\d{1,2}:\d{1,2}:\d{1,2}", str(v))),
     "null or a duration DD:HH:MM:SS"),
    ("trainer.precision", lambda v: str(v) in ("32", "32-true"), "32 (the rasterizers and the mapper work in float32)"),
    ("seed", lambda v: isinstance(v, int) and 0 <= v < 2**32, "an integer in [0, 2^32)"),
    ("ckpt_path", lambda v: v is None or isinstance(v, str), "null or a checkpoint file"),
    ("eval.holdout_every", lambda v: isinstance(v, int) and v >= 0, "an integer >= 0"),
    ("eval.save_renders", lambda v: isinstance(v, int) and v >= 0, "an integer >= 0"),
    ("eval.ply_fit_steps", lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 0, "an integer >= 0"),
    ("eval.ate_align", lambda v: v in ALIGNMENTS, f"one of {', '.join(ALIGNMENTS)}"),
    ("sensor.ate_align", lambda v: v in ALIGNMENTS, f"one of {', '.join(ALIGNMENTS)}"),
    ("eval.lpips_weights", lambda v: v is None or (isinstance(v, str) and Path(v).expanduser().is_file()),
     "null or an existing AlexNet weights file (alexnet-owt-7be5be79.pth)"),
    ("eval.active_opacity", lambda v: _number(v) and 0 <= v < 1, "a number in [0, 1)"),
    ("data.downscale", lambda v: _number(v) and v >= 1, "a number >= 1"),
    ("sensor.mode", lambda v: v in ("mono", "stereo", "rgbd"), "one of mono, stereo, rgbd"),
    ("raster.backend", lambda v: v in ("auto", "torch", "cpu", "cuda"), "one of auto, torch, cpu, cuda"),
    ("raster.near", lambda v: _number(v) and v > 0, "a number > 0 (metres)"),
    ("callbacks.slam_bridge.frames_per_step", lambda v: v is None or (_number(v) and v > 0), "null or a number > 0"),
    ("callbacks.slam_bridge.feed_until", lambda v: _number(v) and 0 < v <= 1, "a fraction in (0, 1]"),
    ("slam_mode", lambda v: v in SLAM_MODES, f"one of {', '.join(SLAM_MODES)}"),
    ("slam_rate", lambda v: _number(v) and v > 0, "a number > 0 (1 = real time)"),
    ("callbacks.slam_bridge.min_initial_keyframes", lambda v: isinstance(v, int) and v >= 1, "an integer >= 1"),
]


@dataclass
class SensorConfig:
    """The `sensor` group (conf/sensor/*.yaml)."""

    mode: str
    ate_align: str


@dataclass
class PathsConfig:
    """The `paths` group (conf/paths/default.yaml)."""

    root_dir: str
    data_dir: str
    log_dir: str
    output_dir: str | None  # Hydra's run folder (None where a config is composed without one)


@dataclass
class LimitsConfig:
    """`limits` (conf/train.yaml)."""

    max_rss_mb: float | None


TYPED_GROUPS = {"sensor": SensorConfig, "paths": PathsConfig, "limits": LimitsConfig}
HYDRA_KEYS = ("_target_", "_partial_", "_recursive_", "_convert_", "_args_")
# targets taking **kwargs -> where those go (their keys are checked against both signatures)
KWARGS_GO_TO = {"lightning.pytorch.loggers.TensorBoardLogger": "torch.utils.tensorboard.SummaryWriter"}


def _known_top_level_keys() -> set[str]:
    """The keys conf/train.yaml writes and the groups of its defaults list."""
    root = OmegaConf.load(CONF_DIR / "train.yaml")
    groups = {d if isinstance(d, str) else next(iter(d)) for d in root.defaults} - {"_self_"}
    return (set(root) - {"defaults"}) | groups


def _check_target_keys(node: dict, where: str) -> None:
    """ConfigError naming the first key of a Hydra `_target_` node that its target does not take
    (a target taking **kwargs accepts any)."""
    from hydra.utils import get_object

    target = node.get("_target_")
    if not isinstance(target, str):
        return
    try:
        params = dict(inspect.signature(get_object(target)).parameters)
        if target in KWARGS_GO_TO:
            params.update(inspect.signature(get_object(KWARGS_GO_TO[target])).parameters)
    except Exception as err:  # noqa: BLE001 - any import or lookup failure means the same to the user
        raise ConfigError(f"{where}._target_={target!r} cannot be loaded ({type(err).__name__})") from None
    params = {k: p for k, p in params.items() if p.kind is not p.VAR_KEYWORD or target not in KWARGS_GO_TO}
    if any(p.kind is p.VAR_KEYWORD for p in params.values()):
        return
    unknown = sorted(k for k in node if k not in HYDRA_KEYS and k not in params)
    if unknown:
        raise ConfigError(f"{where}.{unknown[0]}: unknown key; known keys of {where}: {', '.join(params)}")


def _check_groups(cfg: DictConfig, mapper: bool) -> None:
    """Unknown keys in every group: at the top, in the typed groups (sensor, paths, limits, slam)
    and in the `_target_` nodes (data; with the mapper also trainer, callbacks, logger)."""
    unknown = sorted(set(cfg) - _known_top_level_keys())
    if unknown:
        raise ConfigError(f"{unknown[0]}: unknown key at the top of the config (conf/train.yaml)")
    for key, cls in TYPED_GROUPS.items():
        if OmegaConf.select(cfg, key, default=None) is not None:
            schema.build(cls, OmegaConf.to_container(cfg[key], resolve=True), key)
    if OmegaConf.select(cfg, "slam", default=None) is not None:
        slam_config(OmegaConf.to_container(cfg.slam, resolve=True))
    if OmegaConf.select(cfg, "data", default=None) is not None:
        data = OmegaConf.to_container(cfg.data, resolve=True)
        data.pop("stress", None)  # segs.data.stress's, checked when it wraps the sequence
        _check_target_keys(data, "data")
    if not mapper:
        return
    if OmegaConf.select(cfg, "trainer", default=None) is not None:
        _check_target_keys(OmegaConf.to_container(cfg.trainer, resolve=True), "trainer")
    for group in ("callbacks", "logger"):
        for name, node in (OmegaConf.to_container(cfg[group], resolve=True) if cfg.get(group) else {}).items():
            if node is not None:
                _check_target_keys(node, f"{group}.{name}")


def instantiate(node, *args, **kwargs):
    """hydra.utils.instantiate, with a user-input error raised inside a target re-raised as is.

    Hydra wraps every exception of a target in InstantiationException; a UserInputError (bad
    data path, out-of-range value) must reach the user as its own one-line message.
    """
    from hydra.errors import InstantiationException
    from hydra.utils import instantiate as hydra_instantiate

    try:
        return hydra_instantiate(node, *args, **kwargs)
    except InstantiationException as err:
        cause = err.__cause__
        while cause is not None and not isinstance(cause, UserInputError):
            cause = cause.__cause__
        if cause is not None:
            raise cause from None
        raise


def make_sequence(data_cfg: DictConfig):
    """Instantiate the `data` node; an optional `data.stress` node wraps the sequence.

    data.stress (issue "stability"): {kind, level, ...} passed to segs.data.stress.apply_stress.
    """
    node = OmegaConf.to_container(data_cfg, resolve=True)
    stress = node.pop("stress", None)
    sequence = instantiate(node)
    cam, native = sequence.camera, getattr(sequence, "native_camera", sequence.camera)
    if cam.width < 1 or cam.height < 1:
        raise ConfigError(f"config key data.downscale={node.get('downscale')!r} is out of range: the {native.width}x{native.height} "
                          f"images would be {cam.width}x{cam.height}; expected at most {min(native.width, native.height)}")  # fmt: skip
    if getattr(sequence, "dropped", 0):
        log.warning("data: %d of the frames listed in %s are left out (no depth / right image matches them); "
                    "metrics.json counts them in frames_dropped", sequence.dropped, node.get("root", "the sequence"))  # fmt: skip
    if stress:
        from segs.data.stress import apply_stress

        try:
            sequence = apply_stress(sequence, **stress)
        except TypeError as err:
            raise ConfigError(f"data.stress: {err}") from None
    return sequence


def validate(cfg: DictConfig, mapper: bool = True) -> None:
    """Raise ConfigError naming the first bad key.

    Checks, before anything runs: every number of the config is finite, no group holds an
    unknown key (segs.schema.build for the typed groups, the target's signature for the
    `_target_` nodes: data, trainer, callbacks, logger), the viewer group
    (segs.viewer.config: keys, ranges, viser installed when on), the typed mapper configs
    (model, mapping, raster: unknown / missing keys, kinds, ranges; segs.modules.config) after
    the keys of _CHECKS, raster.far > raster.near, and that raster.backend=cuda can run here.
    mapper=False (segs.track, which builds no mapper) skips the typed mapper configs and the
    raster backend check, and with them importing torch (2-3 s and about 200 MB).
    """
    renamed = OmegaConf.select(cfg, "camera.renamed_to", default=None)
    if renamed is not None:
        raise ConfigError(f"config group camera was renamed sensor: use {renamed}")
    _check_finite(cfg)
    _check_groups(cfg, mapper)
    for key, ok, expected in _CHECKS:
        value = OmegaConf.select(cfg, key, default="__absent__")
        if isinstance(value, str) and value == "__absent__":
            continue
        if not ok(value):
            raise ConfigError(f"config key {key}={value!r} is out of range: expected {expected}")
    if OmegaConf.select(cfg, "eval", default=None) is not None:
        from segs.eval_config import eval_config

        eval_config(cfg.eval)
    if OmegaConf.select(cfg, "viewer", default=None) is not None:
        from segs.viewer.config import viewer_config

        viewer_config(OmegaConf.to_container(cfg.viewer, resolve=True))
    if not mapper:
        return
    from segs.modules.config import mapping_config, model_config, raster_config

    if OmegaConf.select(cfg, "model", default=None) is not None:
        model_config(cfg.model, warn=True)
    for key, build in (("mapping", mapping_config), ("raster", raster_config)):
        if OmegaConf.select(cfg, key, default=None) is not None:
            build(cfg[key])
    near, far = OmegaConf.select(cfg, "raster.near", default=None), OmegaConf.select(cfg, "raster.far", default=None)
    if near is not None and far is not None and not (_number(far) and far > near):
        raise ConfigError(f"config key raster.far={far!r} is out of range: expected a number > raster.near={near!r}")
    if OmegaConf.select(cfg, "raster.backend", default=None) == "cuda":
        from segs.raster._cuda_backend import unavailable_reason

        why = unavailable_reason()
        if why is None and OmegaConf.select(cfg, "trainer.accelerator", default="auto") == "cpu":
            why = "trainer.accelerator=cpu keeps the map on the CPU"
        if why is not None:
            raise ConfigError(f"config key raster.backend='cuda' cannot run here: {why}; use raster.backend=auto")


def _check_finite(cfg: DictConfig) -> None:
    """ConfigError naming the first number of the config (hydra node aside) that is inf or NaN."""
    try:
        tree = OmegaConf.to_container(OmegaConf.masked_copy(cfg, [k for k in cfg if k != "hydra"]), resolve=True)
    except Exception as err:  # noqa: BLE001 - an interpolation that cannot resolve
        raise ConfigError(f"config: {str(err).splitlines()[0]}") from None

    def walk(node, key: str) -> None:
        if isinstance(node, dict):
            for k, v in node.items():
                walk(v, f"{key}.{k}" if key else str(k))
        elif isinstance(node, list):
            for i, v in enumerate(node):
                walk(v, f"{key}[{i}]")
        elif isinstance(node, float) and not math.isfinite(node):
            raise ConfigError(f"config key {key}={node!r} is out of range: expected a finite number")

    walk(tree, "")


@contextlib.contextmanager
def user_errors_exit(code: int = 2) -> Iterator[None]:
    """Turn user-input errors into one line on stderr and a non-zero exit, without traceback."""
    try:
        yield
    except UserInputError as err:
        msg = str(err).splitlines()[0] if str(err) else type(err).__name__
        print(f"error: {msg}", file=sys.stderr)
        raise SystemExit(code) from None


def make_source(cfg: DictConfig, sequence, ahead: int = 0, reader: str = "thread"):
    """The configured frontend tracking `sequence` as a segs.pipeline frame source: built here and
    fed in this process (slam_mode=interleaved; ahead / reader: frames read and prepared ahead of
    tracking, segs.pipeline.readers), or built and run by a child process (slam_mode=process |
    live: ProcessSource / LiveSource; the frontend is also built here once, so a bad slam config
    fails before the child starts)."""
    import functools

    from segs.pipeline.process import LiveSource, ProcessSource
    from segs.pipeline.sources import InterleavedSource

    mode = OmegaConf.select(cfg, "slam_mode", default="interleaved")
    extra = {}
    if mode == "live" and "threaded" in cfg.slam:  # a camera does not wait for local mapping
        extra["threaded"] = True
    factory = functools.partial(instantiate(cfg.slam), camera=sequence.camera, sensor=sequence.sensor, **extra)
    frontend = factory()
    if mode == "interleaved":
        return InterleavedSource(frontend, sequence, ahead=ahead, reader=reader)
    cls = LiveSource if mode == "live" else ProcessSource
    return cls(factory, sequence, frontend.uses_ground_truth_poses, rate=OmegaConf.select(cfg, "slam_rate", default=1.0))
