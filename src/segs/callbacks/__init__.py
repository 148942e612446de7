"""Lightning callbacks: the SLAM bridge, image logging and atomic periodic checkpoints."""
from segs.callbacks.bridge import SlamBridge
from segs.callbacks.checkpoint import PeriodicCheckpoint, save_atomic
from segs.callbacks.logging import ImageLogger

__all__ = ["SlamBridge", "PeriodicCheckpoint", "ImageLogger", "save_atomic"]
