"""segs: SEGS-SLAM (structure-enhanced 3D Gaussian splatting SLAM with appearance embedding)."""

import ctypes
import os
import sys

__version__ = "0.1.0"

# PyTorch's OpenMP threads spin after every operation by default; on a 2-core machine shared
# with anything else that makes training iterations 3-10x slower (docs/decisions/019-omp-wait-policy.md). It must
# be set before torch starts; `python -m segs.*` imports this first. Users may override it.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def _reuse_freed_memory() -> None:
    """glibc: serve allocations up to 64 MB from the heap and keep up to 256 MB of freed heap
    (mallopt M_MMAP_THRESHOLD / M_TRIM_THRESHOLD). By default every array above 128 kB (a frame's
    float image, its pyramid, depth, ...) is a fresh mmap whose pages fault in one by one when
    first written and go back to the kernel when freed: 2.0 million page faults and 7.5 s of
    system time in a 20 s live run of 600 frames, against 70 thousand and 2.2 s with this
    (docs/decisions/018-freed-memory-kept.md). The environment variable
    SEGS_MALLOC=default leaves glibc's settings; other C libraries are left alone."""
    if os.environ.get("SEGS_MALLOC") == "default" or not sys.platform.startswith("linux"):
        return
    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):  # not glibc
        return
    m_trim_threshold, m_mmap_threshold = -1, -3  # glibc's <malloc.h> parameter numbers
    mallopt(m_mmap_threshold, 64 << 20)
    mallopt(m_trim_threshold, 256 << 20)


_reuse_freed_memory()
