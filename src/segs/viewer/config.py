"""The typed `viewer` group (conf/viewer/off.yaml, on.yaml), built by segs.schema.build.

Defaults are written once, in conf/viewer/on.yaml; `viewer=off` holds only `enabled: false`, and
a viewer key given with it is refused (it would do nothing).
"""
from __future__ import annotations

import importlib.util
from dataclasses import dataclass
from typing import Any, Mapping

from segs.errors import ConfigError
from segs.schema import build

EXTRA_HINT = 'pip install -c constraints.txt -e ".[viewer]"'


@dataclass
class ViewerConfig:
    enabled: bool
    host: str
    port: int | None
    first_port: int
    refresh_s: float
    max_share: float
    test_views: int


def viewer_config(node: Mapping[str, Any] | None) -> ViewerConfig | None:
    """The viewer's config, or None for viewer=off; ConfigError naming the key when it is bad."""
    values = dict(node or {})
    if not values.get("enabled", False):
        extra = sorted(k for k in values if k != "enabled")
        if extra:
            raise ConfigError(f"viewer.{extra[0]}: set while the viewer is off; add viewer=on")
        return None
    cfg = build(ViewerConfig, values, "viewer")
    for key, ok, expected in (
        ("port", cfg.port is None or 1 <= cfg.port <= 65535, "null or a port in [1, 65535]"),
        ("first_port", 1 <= cfg.first_port <= 65535, "a port in [1, 65535]"),
        ("refresh_s", cfg.refresh_s > 0, "a number of seconds > 0"),
        ("max_share", 0 < cfg.max_share <= 1, "a fraction in (0, 1]"),
        ("test_views", cfg.test_views >= 0, "an integer >= 0"),
    ):
        if not ok:
            raise ConfigError(f"config key viewer.{key}={getattr(cfg, key)!r} is out of range: expected {expected}")
    if importlib.util.find_spec("viser") is None:
        raise ConfigError(f"viewer=on needs the viser package: {EXTRA_HINT}")
    return cfg
