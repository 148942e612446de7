"""The `eval` config group, typed: built by segs.schema.build inside segs.config.validate, so an
unknown key (`+eval.anything=1`) is a one-line error before any work. The defaults and their
documentation are in conf/train.yaml (`eval:`); this class has none, so a missing key is an
error, never a second default. Imports nothing heavy (segs.track validates it without torch)."""
from __future__ import annotations

from dataclasses import dataclass

from omegaconf import DictConfig, OmegaConf

from segs import schema


@dataclass(frozen=True)
class EvalConfig:
    """Test-view evaluation at the end of a run (segs.evaluation)."""

    enabled: bool
    """render the test views and compute ATE after fit (false: metrics.json says not_evaluated)"""
    holdout_every: int
    """hold every n-th frame out of training as a test view (0: the paper's split, non-keyframes)"""
    lpips_weights: str | None
    """torchvision's AlexNet weights file for LPIPS (null: LPIPS reported as n/a)"""
    save_renders: int
    """test renders written beside their ground truth, spread over the test frames"""
    ate_align: str
    """trajectory alignment of ATE: se3, sim3 (monocular) or none"""
    write_ply: bool
    """write point_cloud.ply (3D-GS layout)"""
    ply_fit_steps: int
    """steps fitting a per-view-decoded map's PLY to the training views as a 3D-GS viewer draws it (0: none)"""
    active_opacity: float
    """opacity above which a Gaussian counts as active (compactness figures)"""
    progress: bool
    """a progress bar over the test views"""


def eval_config(node: DictConfig | dict) -> EvalConfig:
    """The typed `eval` group (ConfigError naming the key when unknown, missing or of the wrong kind)."""
    values = OmegaConf.to_container(node, resolve=True) if isinstance(node, DictConfig) else dict(node)
    return schema.build(EvalConfig, values, "eval")
