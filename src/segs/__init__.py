"""segs: SEGS-SLAM (structure-enhanced 3D Gaussian splatting SLAM with appearance embedding)."""

__version__ = "0.1.0"
