"""Hydra glue shared by the entry points and the tests: config folder, resolvers, validation."""
from __future__ import annotations

import contextlib
import sys
from pathlib import Path
from typing import Callable, Iterator

from omegaconf import DictConfig, OmegaConf

from segs.errors import ConfigError, UserInputError

REPO_ROOT = Path(__file__).resolve().parents[2]
CONF_DIR = REPO_ROOT / "conf"

if not OmegaConf.has_resolver("segs_root"):
    OmegaConf.register_new_resolver("segs_root", lambda: str(REPO_ROOT))


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


# (key, predicate, expectation) checked before anything runs; keys absent from a config are skipped
_CHECKS: list[tuple[str, Callable[[object], bool], str]] = [
    ("trainer.max_steps", lambda v: isinstance(v, int) and v > 0, "an integer > 0"),
    ("seed", lambda v: isinstance(v, int) and v >= 0, "an integer >= 0"),
    ("eval.holdout_every", lambda v: isinstance(v, int) and v >= 0, "an integer >= 0"),
    ("eval.save_renders", lambda v: isinstance(v, int) and v >= 0, "an integer >= 0"),
    ("data.downscale", lambda v: isinstance(v, (int, float)) and v >= 1, "a number >= 1"),
    ("camera.sensor", lambda v: v in ("mono", "stereo", "rgbd"), "one of mono, stereo, rgbd"),
    ("raster.backend", lambda v: v in ("auto", "torch", "cpu", "cuda"), "one of auto, torch, cpu, cuda"),
    ("callbacks.slam_bridge.frames_per_step", lambda v: v is None or (isinstance(v, (int, float)) and v > 0), "null or a number > 0"),
    ("callbacks.slam_bridge.feed_until", lambda v: isinstance(v, (int, float)) and 0 < v <= 1, "a fraction in (0, 1]"),
    ("callbacks.slam_bridge.min_initial_keyframes", lambda v: isinstance(v, int) and v >= 1, "an integer >= 1"),
]


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
    if stress:
        from segs.data.stress import apply_stress

        try:
            sequence = apply_stress(sequence, **stress)
        except TypeError as err:
            raise ConfigError(f"data.stress: {err}") from None
    return sequence


def validate(cfg: DictConfig) -> None:
    """Raise ConfigError naming the first out-of-range key; the model checks its own keys."""
    for key, ok, expected in _CHECKS:
        value = OmegaConf.select(cfg, key, default="__absent__")
        if isinstance(value, str) and value == "__absent__":
            continue
        if not ok(value):
            raise ConfigError(f"config key {key}={value!r} is out of range: expected {expected}")


@contextlib.contextmanager
def user_errors_exit(code: int = 2) -> Iterator[None]:
    """Turn user-input errors into one line on stderr and a non-zero exit, without traceback."""
    try:
        yield
    except UserInputError as err:
        msg = str(err).splitlines()[0] if str(err) else type(err).__name__
        print(f"error: {msg}", file=sys.stderr)
        raise SystemExit(code) from None
