"""Bundle adjustment in a child process, for the threaded mode of the ORB frontend.

gtsam keeps the GIL while it optimises, so a bundle adjustment in the mapping thread would stop
the tracking thread as well; run in a child process it uses another core. The child is a plain
`python -m segs.slam.backend.ba_process` reading pickled requests on stdin and answering on stdout (no
multiprocessing start method, so it works from any main module). Results are the same as
BundleAdjuster's: the problem travels as numpy arrays.
"""
from __future__ import annotations

import pickle
import subprocess
import sys
import threading

import numpy as np

from segs import process_settings
from segs.slam.estimation.optimize import CONVERGED_GAIN, BundleAdjuster


class BundleAdjusterProcess:
    """BundleAdjuster (same constructor and methods) whose `run` executes in a child process,
    started at the first call and ended by `close()` (or when the parent exits)."""

    def __init__(self, K: np.ndarray, bf: float, scales: np.ndarray, huber: bool = True,
                 ur_sigma: float | None = None):
        self._args = (np.asarray(K), float(bf), np.asarray(scales), huber, ur_sigma)
        self._local = BundleAdjuster(*self._args)
        self._proc: subprocess.Popen | None = None
        self._lock = threading.Lock()

    def _start(self) -> subprocess.Popen:
        proc = subprocess.Popen([sys.executable, "-m", "segs.slam.backend.ba_process"], stdin=subprocess.PIPE,
                                stdout=subprocess.PIPE)
        pickle.dump(self._args, proc.stdin, protocol=pickle.HIGHEST_PROTOCOL)
        proc.stdin.flush()
        return proc

    def run(self, poses, fixed, points, obs, iterations):
        """As BundleAdjuster.run, in the child process."""
        return self._call("run", poses, fixed, points, obs, iterations)

    def run_two_pass(self, poses, fixed, points, obs, iterations, min_gain=CONVERGED_GAIN):
        """As BundleAdjuster.run_two_pass, in the child process."""
        return self._call("run_two_pass", poses, fixed, points, obs, iterations, min_gain)

    def _call(self, method: str, *args):
        with self._lock:
            if self._proc is None or self._proc.poll() is not None:
                self._proc = self._start()
            pickle.dump((method, args), self._proc.stdin, protocol=pickle.HIGHEST_PROTOCOL)
            self._proc.stdin.flush()
            try:
                ok, result = pickle.load(self._proc.stdout)
            except EOFError:
                raise RuntimeError("the bundle-adjustment process ended unexpectedly") from None
        if not ok:
            raise RuntimeError(f"bundle adjustment failed in the child process: {result}")
        return result

    def chi2(self, poses, points, obs):
        return self._local.chi2(poses, points, obs)

    def close(self) -> None:
        with self._lock:
            if self._proc is not None:
                self._proc.stdin.close()
                self._proc.wait(timeout=30)
                self._proc = None

    def __del__(self) -> None:
        if getattr(self, "_proc", None) is not None and self._proc.poll() is None:
            self._proc.kill()


def _serve() -> None:
    """Child side: constructor arguments, then ((method, args) -> (ok, result)) until stdin closes."""
    stdin, stdout = sys.stdin.buffer, sys.stdout.buffer
    ba = BundleAdjuster(*pickle.load(stdin))
    while True:
        try:
            request = pickle.load(stdin)
        except EOFError:
            return
        method, args = request
        try:
            if method not in ("run", "run_two_pass"):
                raise ValueError(f"unknown method {method!r}")
            reply = (True, getattr(ba, method)(*args))
        except Exception as exc:  # reported to the parent, which raises
            reply = (False, f"{type(exc).__name__}: {exc}")
        pickle.dump(reply, stdout, protocol=pickle.HIGHEST_PROTOCOL)
        stdout.flush()


if __name__ == "__main__":
    process_settings.apply()
    _serve()
