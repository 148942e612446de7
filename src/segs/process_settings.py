"""Process-wide settings of segs's programs, applied by each entry point before torch loads.

`apply()` is called by the programs, never by an import (docs/decisions/028-process-settings.md):
`python -m segs.train` and `segs.track`, the child processes (`segs.pipeline.process`,
`segs.slam.backend.ba_process`, the frame reader of `segs.pipeline.readers`), the vocabulary
trainer, bench/_harness.py and tests/conftest.py. It sets

- `OMP_WAIT_POLICY=PASSIVE` unless the environment sets it: PyTorch's OpenMP threads spin after
  every operation by default; on a 2-core machine shared with anything else that makes training
  iterations 3-10x slower (docs/decisions/019-omp-wait-policy.md). libgomp reads it once, when
  torch loads: a call after that warns, and the child processes inherit it;
- with it, when the CPUs are idle as the program starts (>= 75 % idle over 0.1 s) and neither
  variable is set: `GOMP_SPINCOUNT=1000`, a short spin before a waiting thread sleeps (a step
  1.25-1.4x faster on an idle machine; docs/decisions/033-omp-spin-when-idle.md);
- with glibc, an allocator that keeps freed heap memory for the next frame (`SEGS_MALLOC=default`
  opts out; docs/decisions/018-freed-memory-kept.md). Per process: each child calls apply() too.

`release_free_memory()` gives the heap's free pages back between phases of a run (segs.train
after training: docs/decisions/029-peak-memory.md).
"""
from __future__ import annotations

import ctypes
import os
import sys
import time
import warnings

# glibc's <malloc.h> parameter numbers and the values set: allocations up to 64 MB from the heap,
# up to 256 MB of freed heap kept
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
MMAP_THRESHOLD, TRIM_THRESHOLD = 64 << 20, 256 << 20
_state = {"malloc": "default"}
# an idle machine: libgomp's threads spin this many times (tens of microseconds) before sleeping,
# instead of sleeping at once (docs/decisions/033-omp-spin-when-idle.md)
SPIN_COUNT, IDLE_SHARE = 1000, 0.75


def apply() -> None:
    """Set OMP_WAIT_POLICY=PASSIVE (unless set), with a short spin on an idle machine, and keep
    freed memory (module doc); idempotent."""
    if "OMP_WAIT_POLICY" not in os.environ:
        if "torch" in sys.modules:
            warnings.warn("segs.process_settings.apply() after torch was imported: OMP_WAIT_POLICY=PASSIVE does not "
                          "reach its OpenMP threads (call apply() before importing torch)", RuntimeWarning, stacklevel=2)
        os.environ["OMP_WAIT_POLICY"] = "PASSIVE"
        if "GOMP_SPINCOUNT" not in os.environ:
            idle = idle_share()
            if idle is not None and idle >= IDLE_SHARE:
                os.environ["GOMP_SPINCOUNT"] = str(SPIN_COUNT)
    _reuse_freed_memory()


def idle_share(seconds: float = 0.1) -> float | None:
    """The share of all CPUs' time spent idle over the next `seconds` (/proc/stat: idle + iowait
    over all jiffies; this process sleeps meanwhile, so it measures the others' load). None where
    /proc/stat cannot be read (not Linux)."""

    def read() -> tuple[int, int]:
        with open("/proc/stat") as f:
            ticks = [int(v) for v in f.readline().split()[1:]]
        return ticks[3] + ticks[4], sum(ticks)

    try:
        idle0, total0 = read()
        time.sleep(seconds)
        idle1, total1 = read()
    except (OSError, ValueError, IndexError):
        return None
    return (idle1 - idle0) / max(total1 - total0, 1)


def release_free_memory() -> bool:
    """glibc: give the free pages of the heap back to the kernel (malloc_trim(0)); what is kept
    for the next allocation (apply()) is worth keeping while a phase repeats itself (training
    steps), not once it has ended. -> whether glibc released any memory (False elsewhere)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        trim = ctypes.CDLL("libc.so.6").malloc_trim
    except (OSError, AttributeError):  # not glibc
        return False
    return bool(trim(0))


def malloc_setting() -> str:
    """"kept" once apply() set glibc's thresholds in this process, else "default" (run records)."""
    return _state["malloc"]


def _reuse_freed_memory() -> None:
    """glibc: serve allocations up to 64 MB from the heap and keep up to 256 MB of freed heap
    (mallopt M_MMAP_THRESHOLD / M_TRIM_THRESHOLD). By default every array above 128 kB (a frame's
    float image, its pyramid, depth, ...) is a fresh mmap whose pages fault in one by one when
    first written and go back to the kernel when freed: 2.0 million page faults and 7.5 s of
    system time in a 20 s live run of 600 frames, against 70 thousand and 2.2 s with this
    (docs/decisions/018-freed-memory-kept.md). SEGS_MALLOC=default leaves glibc's settings;
    other C libraries are left alone."""
    if os.environ.get("SEGS_MALLOC") == "default" or not sys.platform.startswith("linux"):
        return
    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):  # not glibc
        return
    mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD)
    mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD)
    _state["malloc"] = "kept"
