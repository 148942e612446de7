"""What every bench script shares. A script calls `apply_process_settings()` before the imports
that load torch (docs/decisions/process-settings.md)."""
from __future__ import annotations

from segs import process_settings


def apply_process_settings() -> None:
    """segs's process settings (OMP_WAIT_POLICY=PASSIVE unless set, freed memory kept), as the
    programs `python -m segs.*` apply them; call before torch loads."""
    process_settings.apply()
