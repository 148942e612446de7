"""segs: SEGS-SLAM (structure-enhanced 3D Gaussian splatting SLAM with appearance embedding)."""

import os

__version__ = "0.1.0"

# PyTorch's OpenMP threads spin after every operation by default; on a 2-core machine shared
# with anything else that makes training iterations 3-10x slower (docs/performance.md). It must
# be set before torch starts; `python -m segs.*` imports this first. Users may override it.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
