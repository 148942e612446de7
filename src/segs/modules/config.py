"""Typed configs of the mapper: `model` (SEGS or plain 3D-GS), `mapping` and `raster`.

Defaults are written once, in the YAML files (conf/model/segs.yaml, conf/model/plain_3dgs.yaml,
the `mapping:` node of conf/train.yaml, conf/raster/default.yaml), which document them; these dataclasses have no defaults,
so a key missing from a config is an error, never a silent second default. Every config is built
by segs.schema.build (unknown keys and values of the wrong kind: a one-line ConfigError naming
the key) and then range-checked here. segs.config.validate builds them before anything runs.
"""
from __future__ import annotations

import importlib
import logging
from dataclasses import dataclass
from typing import Any, Mapping

from omegaconf import DictConfig, OmegaConf

from segs.errors import ConfigError
from segs.modules.afme import KINDS as APPEARANCE_KINDS
from segs.modules.densification import AdaptiveDensity, AnchorGrowth
from segs.modules.fpr import MODES as FPR_MODES
from segs.schema import build, foreign_keys, without

log = logging.getLogger("segs")


@dataclass
class AppearanceConfig:
    kind: str  # linear (paper AfME) | mlp | ae (ablation) | none
    dim: int
    hidden: int
    max_views: int


@dataclass
class FprConfig:
    enabled: bool
    weight: float  # the FPR loss weight (formerly model.loss.lambda_hf)
    scales: int
    mode: str
    hp_ratio: float
    lp_ratio: float
    from_step: int
    until_step: int


@dataclass
class SegsLoss:
    lambda_dssim: float
    lambda_vol: float


@dataclass
class SegsLr:
    offsets: float
    offsets_final: float
    features: float
    scales: float
    mlp_opacity: float
    mlp_opacity_final: float
    mlp_cov: float
    mlp_cov_final: float
    mlp_color: float
    mlp_color_final: float
    appearance: float
    appearance_final: float


@dataclass
class SegsConfig:
    k: int
    feature_dim: int
    hidden: int
    use_distance: bool
    voxel_size: float
    min_new_points: int
    max_anchors: int
    budget_mb: float | None
    frustum_margin: float
    reference_steps: int
    total_steps: int
    decoder_average: float  # renders outside training decode with the decoders' EMA of this decay (0 = off)
    appearance: AppearanceConfig
    fpr: FprConfig
    loss: SegsLoss
    densify: AnchorGrowth
    lr: SegsLr


@dataclass
class PlainLr:
    means: float
    means_final: float
    sh_dc: float
    sh_rest: float
    opacities: float
    scales: float
    quats: float


@dataclass
class PlainConfig:
    sh_degree: int
    sh_increase_every: int
    lambda_dssim: float
    lambda_depth: float
    init_opacity: float
    max_gaussians: int
    budget_mb: float | None
    total_steps: int
    reference_steps: int
    lr: PlainLr
    densify: AdaptiveDensity


RENDER_FILTERS = ("trained", "fixed")


@dataclass
class MappingConfig:
    """The Lightning module around the scene model (conf/train.yaml `mapping:`)."""

    view_budget: int
    min_scene_extent: float
    adam_eps: float
    num_downscales: int  # coarse-to-fine: first steps at 1/2^n of the image size (0 = off)
    downscale_phase: float  # fraction of the schedule each coarser level lasts
    min_schedule_steps: int  # coarse-to-fine: schedules sized for at least this many steps (0 = the run's)
    render_filter: str  # low-pass of renders at full size: "trained" (as the latest training steps' pixels) or "fixed" (0.3 px^2)
    render_filter_decay: float  # "trained": the pixel area averaged over the latest steps with this decay per step
    compile: bool | None  # torch.compile the model's per-step tensor code (SceneModel.compile_step_code); None: on a CUDA device


@dataclass
class RasterConfig:
    """How the mapper renders (conf/raster/default.yaml; segs.config checks the ranges)."""

    backend: str
    near: float
    far: float
    background: tuple


# model._target_ -> its config; old keys -> their new full key
MODELS: dict[str, type] = {"segs.modules.segs_model.SegsModel": SegsConfig, "segs.modules.plain_gs.PlainGaussians": PlainConfig}
RENAMED = {SegsConfig: {"loss.lambda_hf": "model.fpr.weight"}}


def _check(key: str, ok: bool, value, expected: str) -> None:
    if not ok:
        raise ConfigError(f"{key}={value!r} is out of range: expected {expected}")


def _plain(node: Mapping[str, Any] | DictConfig | None) -> dict:
    return OmegaConf.to_container(node, resolve=True) if isinstance(node, DictConfig) else dict(node or {})


def model_config(node, warn: bool = False) -> SegsConfig | PlainConfig:
    """The typed, range-checked config of the `model` node (chosen by its _target_).

    Keys of the other model (an experiment's SEGS settings under `+ablation=plain_3dgs`) do not
    apply and are dropped (warn: logged, naming them); keys of neither model are errors.
    """
    node = _plain(node)
    target = node.get("_target_")
    if target not in MODELS:
        raise ConfigError(f"model._target_={target!r}: expected one of {', '.join(MODELS)}")
    cls = MODELS[target]
    other = PlainConfig if cls is SegsConfig else SegsConfig
    foreign = foreign_keys(node, cls, other)
    if foreign:
        node = without(node, foreign)
        if warn:
            log.warning("model: %s are %s keys and do not apply to %s; ignored", ", ".join(f"model.{k}" for k in foreign),
                        other.__name__.removesuffix("Config"), target.rpartition(".")[2])  # fmt: skip
    cfg = build(cls, node, "model", renamed=RENAMED.get(cls))
    (_check_segs if cls is SegsConfig else _check_plain)(cfg)
    return cfg


def build_model(node):
    """The scene model of a `model` node: SegsModel or PlainGaussians built from its typed config."""
    cfg = model_config(node)
    module, _, name = _plain(node)["_target_"].rpartition(".")
    return getattr(importlib.import_module(module), name)(cfg)


def mapping_config(node) -> MappingConfig:
    cfg = build(MappingConfig, _plain(node), "mapping")
    _check("config key mapping.view_budget", cfg.view_budget >= 1, cfg.view_budget, "an integer >= 1")
    _check("config key mapping.min_scene_extent", cfg.min_scene_extent > 0, cfg.min_scene_extent, "a number > 0 (metres)")
    _check("config key mapping.adam_eps", cfg.adam_eps > 0, cfg.adam_eps, "a number > 0")
    _check("config key mapping.num_downscales", 0 <= cfg.num_downscales <= 4, cfg.num_downscales, "an integer 0..4")
    _check("config key mapping.downscale_phase", 0 < cfg.downscale_phase and cfg.num_downscales * cfg.downscale_phase <= 1,
           cfg.downscale_phase, "a fraction > 0 with num_downscales * downscale_phase <= 1")  # fmt: skip
    _check("config key mapping.min_schedule_steps", cfg.min_schedule_steps >= 0, cfg.min_schedule_steps, "an integer >= 0")
    _check("config key mapping.render_filter", cfg.render_filter in RENDER_FILTERS, cfg.render_filter, f"one of {RENDER_FILTERS}")
    _check("config key mapping.render_filter_decay", 0 <= cfg.render_filter_decay < 1, cfg.render_filter_decay, "a decay in [0, 1)")
    return cfg


def raster_config(node) -> RasterConfig:
    return build(RasterConfig, _plain(node), "raster")


def _check_common(cfg: SegsConfig | PlainConfig) -> None:
    _check("model.reference_steps", cfg.reference_steps > 0, cfg.reference_steps, "> 0")
    _check("model.total_steps", cfg.total_steps > 0, cfg.total_steps, "> 0")
    _check("model.budget_mb", cfg.budget_mb is None or cfg.budget_mb > 0, cfg.budget_mb, "> 0 (MB) or null")
    for name, v in vars(cfg.lr).items():
        _check(f"model.lr.{name}", v >= 0, v, ">= 0")
    d = cfg.densify
    _check("model.densify.interval", d.interval > 0, d.interval, "> 0")


def _check_segs(cfg: SegsConfig) -> None:
    _check_common(cfg)
    _check("model.k", cfg.k > 0, cfg.k, "an integer > 0")
    _check("model.feature_dim", cfg.feature_dim > 0, cfg.feature_dim, "> 0")
    _check("model.hidden", cfg.hidden > 0, cfg.hidden, "> 0")
    _check("model.voxel_size", cfg.voxel_size > 0, cfg.voxel_size, "> 0 (metres)")
    _check("model.max_anchors", cfg.max_anchors > 0, cfg.max_anchors, "> 0")
    _check("model.decoder_average", 0 <= cfg.decoder_average < 1, cfg.decoder_average, "a decay in [0, 1) (0 = off)")
    app, fpr = cfg.appearance, cfg.fpr
    _check("model.appearance.kind", app.kind in APPEARANCE_KINDS, app.kind, f"one of {APPEARANCE_KINDS}")
    _check("model.appearance.dim", app.kind == "none" or app.dim > 0, app.dim, "> 0")
    _check("model.appearance.max_views", app.max_views > 0, app.max_views, "> 0")
    _check("model.fpr.mode", fpr.mode in FPR_MODES, fpr.mode, f"one of {FPR_MODES}")
    _check("model.fpr.scales", fpr.scales >= 1, fpr.scales, ">= 1")
    _check("model.fpr.weight", fpr.weight >= 0, fpr.weight, ">= 0")
    for name, v in vars(cfg.loss).items():
        _check(f"model.loss.{name}", v >= 0, v, ">= 0")


def _check_plain(cfg: PlainConfig) -> None:
    _check_common(cfg)
    _check("model.sh_degree", 0 <= cfg.sh_degree <= 3, cfg.sh_degree, "0..3")
    _check("model.init_opacity", 0 < cfg.init_opacity < 1, cfg.init_opacity, "(0, 1)")
    _check("model.max_gaussians", cfg.max_gaussians > 0, cfg.max_gaussians, "> 0")
