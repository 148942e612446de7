"""segs: SEGS-SLAM (structure-enhanced 3D Gaussian splatting SLAM with appearance embedding).

Importing segs changes nothing process-wide: the programs apply the process settings
(OMP_WAIT_POLICY, the allocator) themselves, before torch loads (segs.process_settings)."""

__version__ = "0.1.0"
