"""segs.data: Frame/Camera/Sequence records and the dataset readers.

Readers (each also a Hydra ``_target_``): :class:`segs.data.tum.TumSequence`,
:class:`segs.data.replica.ReplicaSequence`, :class:`segs.data.euroc.EurocSequence`, :class:`segs.data.seven_scenes.SevenScenesSequence`,
:class:`segs.data.kitti.KittiSequence`,
:class:`segs.data.synthetic.SyntheticSequence`; :class:`segs.data.base.Downscaled` wraps any of
them; :func:`segs.data.factory.build_sequence` picks one by name. Names are imported lazily so
that ``import segs.data.frame`` stays cheap.
"""
from __future__ import annotations

import importlib

_EXPORTS = {
    "Camera": "segs.data.frame",
    "Frame": "segs.data.frame",
    "Sequence": "segs.data.frame",
    "SENSORS": "segs.data.frame",
    "Downscaled": "segs.data.base",
    "TumSequence": "segs.data.tum",
    "ReplicaSequence": "segs.data.replica",
    "EurocSequence": "segs.data.euroc",
    "SevenScenesSequence": "segs.data.seven_scenes",
    "KittiSequence": "segs.data.kitti",
    "SyntheticSequence": "segs.data.synthetic",
    "build_sequence": "segs.data.factory",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'segs.data' has no attribute {name!r}")
