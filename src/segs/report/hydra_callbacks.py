"""Hydra callbacks of the sweeps (conf/sweep/*.yaml, under hydra.callbacks).

RecordFailure: a job that raised leaves ``job_failed.txt`` (exception and traceback) in its
folder, so that the report names the error of every crashed job. Hydra records the failure and
goes on with the other jobs of the batch; the multirun exits non-zero at the end.
ReportOnMultirunEnd: writes the report into the sweep folder when every job succeeded (after a
failure run ``python -m segs.report SWEEP_DIR`` yourself: Hydra skips this hook then).
"""
from __future__ import annotations

import logging
import traceback
from pathlib import Path

from hydra.core.utils import JobStatus
from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from segs.report.runs import FAILURE_FILE

log = logging.getLogger(__name__)


class RecordFailure(Callback):
    """On a failed job, write its exception and traceback to <job folder>/job_failed.txt."""

    def on_job_end(self, config: DictConfig, job_return, **kwargs) -> None:
        if job_return.status != JobStatus.FAILED:
            return
        err = job_return._return_value
        text = f"{type(err).__name__}: {' '.join(str(err).split())}"[:500] + "\n\n"  # first line: the error
        text += "".join(traceback.format_exception(type(err), err, err.__traceback__))
        out = Path(config.hydra.runtime.output_dir) / FAILURE_FILE
        out.write_text(text)
        log.error("job %s failed: %s (see %s)", config.hydra.job.num, text.splitlines()[0], out)


class ReportOnMultirunEnd(Callback):
    """After a multirun whose jobs all returned, write the report into the sweep folder."""

    def on_multirun_end(self, config: DictConfig, **kwargs) -> None:
        from segs.report.write import write_report

        sweep_dir = Path(config.hydra.sweep.dir)
        try:
            written = write_report([sweep_dir])
        except Exception as err:  # noqa: BLE001 - a report problem must not fail the finished sweep
            log.error("segs.report failed on %s: %s", sweep_dir, err)
            return
        log.info("segs.report: %s", written["markdown"])
