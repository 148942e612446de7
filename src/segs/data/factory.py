"""build_sequence: one entry point over every reader (the classes are Hydra targets too)."""
from __future__ import annotations

from pathlib import Path

from segs.data.base import Downscaled
from segs.data.frame import Sequence
from segs.errors import ConfigError

KINDS = {
    "tum": "segs.data.tum:TumSequence",
    "replica": "segs.data.replica:ReplicaSequence",
    "euroc": "segs.data.euroc:EurocSequence",
    "seven_scenes": "segs.data.seven_scenes:SevenScenesSequence",
    "kitti": "segs.data.kitti:KittiSequence",
    "synthetic": "segs.data.synthetic:SyntheticSequence",
}


def build_sequence(kind: str, root: str | Path | None = None, sensor: str = "rgbd", **kwargs) -> Sequence:
    """A sequence of dataset `kind` ("tum", "replica", "euroc", "seven_scenes", "kitti", "synthetic") in sensor mode.

    root is the dataset folder (unused for "synthetic"); kwargs go to the reader's constructor.
    downscale=k is accepted for every kind (SyntheticSequence is wrapped in :class:`Downscaled`).
    """
    if kind not in KINDS:
        raise ConfigError(f"data kind must be one of {', '.join(KINDS)}, got {kind!r}")
    module, cls = KINDS[kind].split(":")
    target = getattr(__import__(module, fromlist=[cls]), cls)
    if kind != "synthetic":
        if root is None:
            raise ConfigError(f"data kind {kind!r} needs a root folder")
        return target(root=root, sensor=sensor, **kwargs)
    factor = kwargs.pop("downscale", 1)
    seq = target(sensor=sensor, **kwargs)
    return seq if float(factor) == 1 else Downscaled(seq, factor)
