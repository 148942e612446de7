"""Assemble report.md, runs.csv and the charts of a set of runs."""
from __future__ import annotations

import datetime
import os
import platform
from pathlib import Path

from segs.report.charts import compactness_chart, speed_accuracy_chart, stability_chart
from segs.report.runs import collect
from segs.report.table import compactness_table, crash_summary, runs_table, stability_table, write_csv


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def default_out(dirs: list[Path]) -> Path:
    """The single folder given, else the common parent of the folders."""
    if len(dirs) == 1:
        return dirs[0]
    return Path(os.path.commonpath([d.resolve() for d in dirs]))


def write_report(dirs, out=None, min_tracked: float = 0.9, max_ate_m: float = 0.05) -> dict[str, Path]:
    """Write report.md, runs.csv and the PNG charts; returns {name: path} of the files written."""
    dirs = [Path(d) for d in dirs]
    runs = collect(dirs)
    out = Path(out) if out is not None else default_out(dirs)
    out.mkdir(parents=True, exist_ok=True)
    written = {"csv": out / "runs.csv"}
    write_csv(written["csv"], runs)
    charts = {
        "speed_accuracy": speed_accuracy_chart(runs, out / "speed_accuracy.png"),
        "compactness": compactness_chart(runs, out / "compactness.png"),
        "stability": stability_chart(runs, out / "stability.png", min_tracked, max_ate_m),
    }
    written.update({k: v for k, v in charts.items() if v is not None})
    root = dirs[0] if len(dirs) == 1 else default_out(dirs)
    sections = [
        "# segs report",
        f"Runs under {', '.join(f'`{d}`' for d in dirs)}; report written {datetime.datetime.now():%Y-%m-%d %H:%M} "
        f"on {_cpu_model()} ({os.cpu_count()} cores) by `python -m segs.report`.",
        "## Jobs\n\n" + crash_summary(runs),
        "## Runs\n\n" + runs_table(runs, root),
    ]
    titles = {"speed_accuracy": "Speed vs accuracy", "compactness": "Compactness", "stability": "Stability"}
    for name, path in charts.items():
        if path is not None:
            sections.append(f"## {titles[name]}\n\n![{titles[name]}]({os.path.relpath(path, out)})")
        if name == "compactness" and compactness_table(runs):
            sections.append(compactness_table(runs))
    stability = stability_table(runs, min_tracked, max_ate_m)
    if stability:
        sections.append(stability)
    written["markdown"] = out / "report.md"
    written["markdown"].write_text("\n\n".join(sections) + "\n")
    return written
