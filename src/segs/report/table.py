"""Markdown tables of a set of runs: every run, stability per stress level, crashes.

Every number comes from a run's metrics.json; a missing or null value is printed as "n/a" and a
run without metrics.json as its status (failed / no metrics / not started), never as numbers.
"""
from __future__ import annotations

import csv
from pathlib import Path

from segs.report.runs import Run, common_overrides, variant

# (header, metrics.json key, format, scale)
COLUMNS = [
    ("PSNR", "psnr", ".2f", 1),
    ("SSIM", "ssim", ".3f", 1),
    ("LPIPS", "lpips", ".3f", 1),
    ("ATE cm", "ate_rmse_m", ".2f", 100),
    ("tracked %", "tracked_fraction", ".0f", 100),
    ("wall s", "wall_time_s", ".0f", 1),
    ("mapping s", "mapping_time_s", ".0f", 1),
    ("iters", "iterations", "d", 1),
    ("it/s", "iterations_per_s", ".2f", 1),
    ("track FPS", "tracking_fps", ".1f", 1),
    ("anchors", "anchors", "d", 1),
    ("Gaussians", "gaussians", "d", 1),
    ("active", "active_gaussians", ".0f", 1),
    ("params", "params", "d", 1),
    ("MB", "model_mb", ".3g", 1),
]


def fmt(value, spec: str, scale: float = 1) -> str:
    """A number formatted, or n/a."""
    if value is None:
        return "n/a"
    value = value * scale
    return format(int(round(value)) if spec == "d" else value, spec)


def _cell(text: str) -> str:
    return text.replace("|", "\\|") or "(none)"


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


def _run_name(run: Run, root: Path | None) -> str:
    if not run.started:
        return "(not started)"
    try:
        return str(run.path.resolve().relative_to(root.resolve())) if root else run.path.name
    except ValueError:
        return run.path.name


def runs_table(runs: list[Run], root: Path | None = None) -> str:
    """One row per run: folder, method, own overrides, status, then every metric column."""
    common = common_overrides(runs)
    header = ["run", "method", "overrides", "status"] + [c[0] for c in COLUMNS]
    rows = []
    for r in runs:
        row = [_run_name(r, root), r.method, _cell(variant(r, common)), r.status if not r.failure else f"failed: {r.failure[:80]}"]
        row = [_cell(c) for c in row]
        row += [fmt(r.metric(key), spec, scale) for _, key, spec, scale in COLUMNS]
        rows.append(row)
    shared = " ".join(f"`{o}`" for o in common) or "(none)"
    return f"Overrides shared by every run: {shared}\n\n" + markdown_table(header, rows)


def series_key(run: Run, runs: list[Run]) -> str:
    """Series label: the method, with the frontend / experiment when those differ between runs."""
    label = run.method
    for group in ("slam", "experiment"):
        if run.choices and len({str(r.choices.get(group)) for r in runs if r.choices}) > 1:
            label += f" {group}={run.choices.get(group)}"
    return label


def reference_run(runs: list[Run], all_runs: list[Run]) -> Run | None:
    """The run of a series without own overrides ("default" or the method's own variant)."""
    common = common_overrides(all_runs)
    return next((r for r in runs if variant(r, common) in ("", "default", r.method)), None)


def compactness_table(runs: list[Run]) -> str:
    """Per series and scene with a reference run: every run's size and PSNR against the reference."""
    common = common_overrides(runs)
    header = ["method", "variant", "MB", "size vs ref", "Gaussians", "active", "PSNR", "PSNR vs ref", "mapping s"]
    rows = []
    done = [r for r in runs if r.metric("psnr") is not None and r.metric("model_mb") is not None]
    for key in dict.fromkeys((r.experiment, series_key(r, runs)) for r in done):
        series = [r for r in done if (r.experiment, series_key(r, runs)) == key]
        ref = reference_run(series, runs)
        if ref is None:
            continue
        for r in series:
            size = r.metric("model_mb") / max(ref.metric("model_mb"), 1e-12)
            rows.append([key[1], variant(r, common) or r.method, fmt(r.metric("model_mb"), ".3g"), f"{size:.0%}",
                         fmt(r.metric("gaussians"), "d"), fmt(r.metric("active_gaussians"), ".0f"), fmt(r.metric("psnr"), ".2f"),
                         f"{r.metric('psnr') - ref.metric('psnr'):+.2f}", fmt(r.metric("mapping_time_s"), ".0f")])  # fmt: skip
    if not rows:
        return ""
    return ("Each run against its series' reference run (no own overrides: `default` / the method itself).\n\n"
            + markdown_table(header, [[_cell(c) for c in row] for row in rows]))


def failed(run: Run, min_tracked: float, max_ate_m: float) -> bool:
    """A stability failure: crashed, too few frames tracked, or ATE above the bound."""
    if run.crashed:
        return True
    if not run.started:
        return False
    tracked, ate = run.metric("tracked_fraction"), run.metric("ate_rmse_m")
    return tracked is None or tracked < min_tracked or ate is None or ate > max_ate_m


def stress_groups(runs: list[Run]) -> dict[str, dict[str, list[Run]]]:
    """kind -> series -> runs sorted by level; unstressed / level-0 runs join every kind at 0."""
    runs = [r for r in runs if not r.superseded]
    kinds = sorted({r.stress[0] for r in runs if r.stress[0] and r.stress[1] > 0})
    out: dict[str, dict[str, list[Run]]] = {}
    for kind in kinds:
        for r in runs:
            k, level = r.stress
            if k == kind or level == 0:
                out.setdefault(kind, {}).setdefault(series_key(r, runs), []).append(r)
    for kind in out.values():
        for series in kind.values():
            series.sort(key=lambda r: r.stress[1])
    return out


def _stability_cell(r: Run) -> str:
    if not r.started:
        return "not started"
    if r.crashed:
        kind = (r.failure or "").split(":", 1)[0]
        return f"**CRASH {kind}**" if kind.isidentifier() else "**CRASH**" if r.failure else "**no metrics**"
    ate = fmt(r.metric("ate_rmse_m"), ".1f", 100)
    return f"{ate} / {fmt(r.metric('tracked_fraction'), '.0f', 100)}% / {fmt(r.metric('psnr'), '.1f')}"


def stability_table(runs: list[Run], min_tracked: float = 0.9, max_ate_m: float = 0.05) -> str:
    """Per stress kind and series: ATE cm / tracked % / PSNR at each level, first failing level."""
    groups = stress_groups(runs)
    if not groups:
        return ""
    blocks = [f"Cells: ATE cm / frames tracked % / test PSNR dB (against the stressed test frames). A level *fails* "
              f"when the job left no metrics.json (**CRASH** and the exception type: it raised; **no metrics**: "
              f"crashed, killed or still running), tracked < {min_tracked:.0%} or ATE > {max_ate_m * 100:g} cm. crashes: jobs without "
              f"metrics.json."]  # fmt: skip
    for kind, series in groups.items():
        levels = sorted({r.stress[1] for rs in series.values() for r in rs})
        header = ["method"] + [f"{kind} {lv:g}" for lv in levels] + ["fails from", "crashes"]
        rows = []
        for name, rs in series.items():
            by_level = {r.stress[1]: r for r in rs}
            first = next((lv for lv in levels if lv in by_level and failed(by_level[lv], min_tracked, max_ate_m)), None)
            cells = [_stability_cell(by_level[lv]) if lv in by_level else "-" for lv in levels]
            rows.append([name] + cells + ["none" if first is None else f"{first:g}", str(sum(r.crashed for r in rs))])
        blocks.append(f"### {kind}\n\n" + markdown_table(header, rows))
    return "\n\n".join(blocks)


def crash_summary(runs: list[Run]) -> str:
    """Counts of finished / crashed / never started jobs, and the crashed folders with their error."""
    crashed = [r for r in runs if r.crashed]
    missing = [r for r in runs if not r.started]
    lost = sum(r.status == "tracking_failed" for r in runs)
    unevaluated = sum(r.status == "not_evaluated" for r in runs)
    text = (f"{len(runs)} jobs: {sum(r.status == 'finished' for r in runs)} finished, "
            + (f"{unevaluated} trained without evaluation (eval.enabled=false), " if unevaluated else "")
            + (f"{lost} tracking failed (no keyframe to map; recorded in metrics.json), " if lost else "")
            + f"{len(crashed)} crashed or unfinished (no metrics.json), {len(missing)} never started.")  # fmt: skip
    if any(r.superseded for r in runs):
        text += f" {sum(r.superseded for r in runs)} unfinished jobs were run again (superseded)."
    lines = [f"- `{r.path}`: {r.failure or 'no metrics.json (crashed, killed or still running)'}" for r in crashed]
    lines += [f"- not started: `{' '.join(r.overrides)}`" for r in missing]
    return "\n".join([text] + lines)


def write_csv(path: Path, runs: list[Run]) -> None:
    """runs.csv: folder, method, status, overrides and every metric column (empty = n/a)."""
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["run", "method", "status", "overrides", "stress_kind", "stress_level"] + [c[1] for c in COLUMNS])
        for r in runs:
            kind, level = r.stress
            values = ["" if r.metric(key) is None else r.metric(key) for _, key, _, _ in COLUMNS]
            writer.writerow([str(r.path), r.method, r.status, " ".join(r.overrides), kind or "", level] + values)
