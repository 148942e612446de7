"""`python -m segs.report DIR...`: tables and charts from the run folders of Hydra (multi)runs.

Reads metrics.json and .hydra/{overrides,config,hydra}.yaml of every run under the given run or
multirun folders and writes into the output folder (by default the one folder given, or the
folders' common parent):

- ``report.md``: job counts and crashes, one table row per run (its own overrides, PSNR, SSIM,
  LPIPS or n/a, ATE, wall time, iterations/s, tracking FPS, anchors, Gaussians, MB, ...), the
  stability table (per stress kind, method and level) and links to the charts;
- ``runs.csv``: the same numbers, machine readable;
- ``speed_accuracy.png``: test PSNR against mapping wall time and against iterations, one series
  per method / ablation, with the Pareto front;
- ``compactness.png``: test PSNR against model size (MB) and Gaussian count (all and active),
  with each series' default run as a dotted line and the PSNR / size change of every other run;
- ``stability.png`` (when runs set data.stress): ATE, fraction of frames tracked and test PSNR
  against the stress level, per kind and method; crashes as red crosses.

A chart is only drawn from what runs measured; runs without metrics.json count as crashes.
"""
from __future__ import annotations

from segs.report.runs import Run, collect
from segs.report.write import write_report

__all__ = ["Run", "collect", "write_report"]
