"""Lightning callbacks: the SLAM bridge, image logging, the progress bar and atomic periodic checkpoints."""
from segs.callbacks.bridge import SlamBridge
from segs.callbacks.checkpoint import PeriodicCheckpoint, save_atomic
from segs.callbacks.interrupt import GracefulInterrupt
from segs.callbacks.logging import ImageLogger, StepProgressBar
from segs.callbacks.memory import MemoryGuard

__all__ = ["SlamBridge", "PeriodicCheckpoint", "ImageLogger", "GracefulInterrupt", "MemoryGuard", "StepProgressBar", "save_atomic"]
