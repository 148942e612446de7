"""When a periodic callback acts: every n steps, at most once per a minimum interval."""
from __future__ import annotations

import math
import time


class StepCadence:
    """Due on the steps that are multiples of `every_n_steps` (0 = never) and come at least
    `min_interval_s` seconds (time.monotonic) after the last `done()`; the first due step counts
    from `restart()`, or acts at once without one. On a fast device the interval keeps a
    step-counted write from becoming a share of the run."""

    def __init__(self, every_n_steps: int, min_interval_s: float = 0.0):
        self.every_n_steps = every_n_steps
        self.min_interval_s = min_interval_s
        self._last = -math.inf

    def restart(self) -> None:
        """The interval counts from now (e.g. the start of training)."""
        self._last = time.monotonic()

    def due(self, step: int) -> bool:
        return (bool(self.every_n_steps) and step % self.every_n_steps == 0
                and time.monotonic() - self._last >= self.min_interval_s)  # fmt: skip

    def done(self) -> None:
        self._last = time.monotonic()
