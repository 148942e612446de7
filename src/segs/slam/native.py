"""The tracker's C++ matching kernel (src/segs/slam/csrc/match.cpp), built on first use.

`best_two_in_radius` is the projection search's inner loop (grid radius query, filters, Hamming
distances, best and second-best candidate per query) with the same results as the numpy pipeline
it replaces; tests/test_slam_units.py compares the two. Without a compiler, or with
``SEGS_SLAM_NO_CPU=1``, `kernels()` returns None and the numpy pipeline runs (same results,
slower). The build shares the rasterizer's cache and flags (segs.raster._build), except that
floating-point contraction is off so that distances round as numpy rounds them.
"""
from __future__ import annotations

import warnings
from pathlib import Path
from types import ModuleType

from segs.raster._build import BuildError, KernelBuild

MATCH = KernelBuild("segs_slam_cpu", Path(__file__).parent / "csrc", ("match.cpp", "map.cpp"), (), "SEGS_SLAM_NO_CPU",
                    fp_contract="off")
_warned = False


def kernels() -> ModuleType | None:
    """The compiled module, or None (one warning per process saying why) where it cannot be built."""
    global _warned
    try:
        return MATCH.load()
    except BuildError as exc:
        if not _warned:
            _warned = True
            warnings.warn(f"segs.slam: C++ matching kernel unavailable ({exc}); using numpy", stacklevel=2)
        return None
