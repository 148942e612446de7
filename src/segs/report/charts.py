"""PNG charts of a set of runs (matplotlib, object API: no pyplot state, no display needed).

Only finished runs are plotted, with the numbers of their metrics.json; crashed jobs appear in
the stability chart as red crosses at their level. One row of panels per scene (experiment)
when a report spans several, since PSNR is not comparable between scenes.
"""
from __future__ import annotations

from pathlib import Path

from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from segs.report.runs import Run, common_overrides, variant
from segs.report.table import failed, reference_run, series_key, stress_groups

MARKERS = "osD^vP*Xh<>p"


def _colours(names: list[str]) -> dict[str, tuple]:
    from matplotlib import colormaps

    cmap = colormaps["tab10"]
    return {n: cmap(i % 10) for i, n in enumerate(names)}


def _marker(name: str, colours: dict) -> str:
    """The same marker for a series in every panel (its place in the colour table)."""
    return MARKERS[list(colours).index(name) % len(MARKERS)]


def _scenes(runs: list[Run]) -> dict[str, list[Run]]:
    out: dict[str, list[Run]] = {}
    for r in runs:
        out.setdefault(r.experiment, []).append(r)
    return out


def pareto_front(points: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """Points not dominated by another (lower or equal x and higher y): the best y per cost x."""
    front: list[tuple[float, float]] = []
    for x, y in sorted(points, key=lambda p: (p[0], -p[1])):
        if not front or y > front[-1][1]:
            front.append((x, y))
    return front


def _finished(runs: list[Run], *keys: str) -> list[Run]:
    return [r for r in runs if r.metrics is not None and all(r.metric(k) is not None for k in keys)]


LINESTYLES = ("-", "--", ":", "-.")


def _scatter(ax, runs: list[Run], all_runs: list[Run], xkey: str, colours: dict, label_skip=(), front=False,
             labels: bool = True, line_skip=("trainer.max_steps",)) -> None:  # fmt: skip
    """PSNR against metrics[xkey], one colour per series.

    Runs of a series that differ only in `line_skip` keys (the iteration budget) are joined by a
    line and labelled once, at its last point; other runs are labelled by their own overrides.
    """
    done = _finished(runs, xkey, "psnr")
    common = common_overrides(all_runs)
    for name in sorted({series_key(r, all_runs) for r in done}):
        pts = [r for r in done if series_key(r, all_runs) == name]
        ax.scatter([r.metric(xkey) for r in pts], [r.metric("psnr") for r in pts], color=colours[name],
                   marker=_marker(name, colours), label=name, zorder=3)  # fmt: skip
        groups: dict[str, list[Run]] = {}
        for r in pts:
            groups.setdefault(variant(r, common, tuple(label_skip) + tuple(line_skip)), []).append(r)
        for i, (label, rs) in enumerate(groups.items()):
            rs.sort(key=lambda r: r.metric(xkey))
            if len(rs) > 1:
                ax.plot([r.metric(xkey) for r in rs], [r.metric("psnr") for r in rs], color=colours[name],
                        ls=LINESTYLES[i % len(LINESTYLES)], lw=0.8, zorder=2)  # fmt: skip
            for r in rs[-1:] if len(rs) > 1 else rs:
                text = label if len(rs) > 1 else variant(r, common, label_skip)
                if labels and text:
                    ax.annotate(text, (r.metric(xkey), r.metric("psnr")), fontsize=6, xytext=(3, 3),
                                textcoords="offset points", color=colours[name])  # fmt: skip
    if front and done:
        pf = pareto_front([(r.metric(xkey), r.metric("psnr")) for r in done])
        ax.step([p[0] for p in pf], [p[1] for p in pf], where="post", color="k", ls="--", lw=1,
                label="Pareto front", zorder=2)  # fmt: skip
    ax.set_ylabel("test PSNR (dB)")
    ax.grid(alpha=0.3)


def _save(fig: Figure, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return path


def _header(fig: Figure, title: str, runs: list[Run]) -> None:
    shared = " ".join(common_overrides(runs))
    fig.suptitle(f"{title}\n{shared}" if shared else title, fontsize=9)


def speed_accuracy_chart(runs: list[Run], path: Path) -> Path | None:
    """PSNR against mapping wall time and against iterations, Pareto fronts drawn."""
    scenes = {k: v for k, v in _scenes(runs).items() if _finished(v, "psnr", "mapping_time_s")}
    if not scenes:
        return None
    colours = _colours(sorted({series_key(r, runs) for r in runs}))
    fig = Figure(figsize=(12, 4.8 * len(scenes)))
    for row, (scene, rs) in enumerate(scenes.items()):
        ax1, ax2 = fig.add_subplot(len(scenes), 2, 2 * row + 1), fig.add_subplot(len(scenes), 2, 2 * row + 2)
        _scatter(ax1, rs, runs, "mapping_time_s", colours, front=True)
        _scatter(ax2, rs, runs, "iterations", colours, front=True)
        ax1.set(xscale="log", xlabel="mapping wall time (s)", title=f"{scene}: accuracy vs mapping time (lines: same run but the budget)")
        ax2.set(xscale="log", xlabel="iterations", title=f"{scene}: accuracy vs iterations")
        ax1.legend(fontsize=7)
    _header(fig, "Speed vs accuracy", runs)
    return _save(fig, path)


def _reference_lines(ax, rs: list[Run], all_runs: list[Run], colours: dict) -> None:
    """Dotted line at each series' reference run; every point labelled with its PSNR / size change."""
    common = common_overrides(all_runs)
    done = _finished(rs, "psnr", "model_mb")
    for name in sorted({series_key(r, all_runs) for r in done}):
        pts = [r for r in done if series_key(r, all_runs) == name]
        ref = reference_run(pts, all_runs)
        if ref is not None:
            ax.axhline(ref.metric("psnr"), color=colours[name], ls=":", lw=1)
        for r in pts:
            label = variant(r, common) or r.method
            if ref is not None and r is not ref:
                delta = r.metric("psnr") - ref.metric("psnr")
                label += f" {delta:+.2f} dB, {r.metric('model_mb') / max(ref.metric('model_mb'), 1e-12):.0%} MB"
            ax.annotate(label, (r.metric("model_mb"), r.metric("psnr")), fontsize=6, xytext=(3, 3),
                        textcoords="offset points", color=colours[name])  # fmt: skip


def compactness_chart(runs: list[Run], path: Path) -> Path | None:
    """PSNR against model size (MB) and against Gaussians (filled: all, hollow: active)."""
    scenes = {k: v for k, v in _scenes(runs).items() if _finished(v, "psnr", "model_mb")}
    if not scenes:
        return None
    colours = _colours(sorted({series_key(r, runs) for r in runs}))
    fig = Figure(figsize=(12, 4.8 * len(scenes)))
    for row, (scene, rs) in enumerate(scenes.items()):
        ax1, ax2 = fig.add_subplot(len(scenes), 2, 2 * row + 1), fig.add_subplot(len(scenes), 2, 2 * row + 2)
        _scatter(ax1, rs, runs, "model_mb", colours, labels=False)
        _reference_lines(ax1, rs, runs, colours)
        _scatter(ax2, rs, runs, "gaussians", colours, line_skip=())
        for r in _finished(rs, "active_gaussians", "psnr", "gaussians"):
            c = colours[series_key(r, runs)]
            ax2.scatter([r.metric("active_gaussians")], [r.metric("psnr")], facecolors="none", edgecolors=[c], zorder=3)
            ax2.plot([r.metric("active_gaussians"), r.metric("gaussians")], [r.metric("psnr")] * 2, color=c, lw=0.6, alpha=0.5)
        ax1.set(xscale="log", xlabel="model size (MB)", title=f"{scene}: accuracy vs model size (dotted: default)")
        ax2.set(xscale="log", xlabel="Gaussians (filled: all; hollow: active, opacity > eval.active_opacity)",
                title=f"{scene}: accuracy vs Gaussian count")  # fmt: skip
        ax1.legend(fontsize=7)
    _header(fig, "Compactness", runs)
    return _save(fig, path)


STABILITY_PANELS = [("ate_rmse_m", "ATE RMSE (cm)", 100.0), ("tracked_fraction", "frames tracked (%)", 100.0),
                    ("psnr", "test PSNR (dB)", 1.0)]  # fmt: skip


def _stability_row(axes, kind: str, series: dict[str, list[Run]], colours: dict, min_tracked, max_ate_m) -> None:
    for name, rs in series.items():
        for ax, (key, _, scale) in zip(axes, STABILITY_PANELS):
            pts = [(r.stress[1], r.metric(key) * scale) for r in rs if r.metric(key) is not None]
            if pts:
                ax.plot(*zip(*pts), marker=_marker(name, colours), color=colours[name], label=name)
            fails = [r.stress[1] for r in rs if not r.crashed and failed(r, min_tracked, max_ate_m)]
            crashes = [r.stress[1] for r in rs if r.crashed]
            ax.scatter(fails, [0.02] * len(fails), transform=ax.get_xaxis_transform(), marker="v", color=colours[name],
                       s=30, zorder=4)  # fmt: skip
            ax.scatter(crashes, [0.06] * len(crashes), transform=ax.get_xaxis_transform(), marker="x", color="red",
                       s=50, zorder=4)  # fmt: skip
    levels = sorted({r.stress[1] for rs in series.values() for r in rs})
    pad = 0.05 * (levels[-1] - levels[0] or 1.0)
    for ax, (key, label, _) in zip(axes, STABILITY_PANELS):
        ax.set(xlabel=f"{kind} level", ylabel=label, xlim=(levels[0] - pad, levels[-1] + pad))
        ax.set_xticks(levels, [f"{lv:g}" for lv in levels], fontsize=7)
        if key == "tracked_fraction":
            ax.set_ylim(-5, 105)
        elif key == "ate_rmse_m":
            ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)


def stability_chart(runs: list[Run], path: Path, min_tracked: float = 0.9, max_ate_m: float = 0.05) -> Path | None:
    """Per stress kind (rows): ATE, fraction tracked and test PSNR (columns) against the level."""
    groups = stress_groups(runs)
    if not groups:
        return None
    colours = _colours(sorted({series_key(r, runs) for r in runs}))
    fig = Figure(figsize=(13, 3.2 * len(groups) + 0.8))
    for row, (kind, series) in enumerate(groups.items()):
        axes = [fig.add_subplot(len(groups), 3, 3 * row + c + 1) for c in range(3)]
        _stability_row(axes, kind, series, colours, min_tracked, max_ate_m)
        axes[0].set_title(kind, loc="left", fontsize=9, fontweight="bold")
    handles = [Line2D([], [], color=c, marker=_marker(n, colours), label=n) for n, c in colours.items()]
    fails = f"fails (tracked < {min_tracked:.0%} or ATE > {max_ate_m * 100:g} cm)"
    handles += [Line2D([], [], ls="", marker="v", color="grey", label=fails),
                Line2D([], [], ls="", marker="x", color="red", label="crash / no metrics.json")]  # fmt: skip
    fig.legend(handles=handles, loc="lower center", ncol=min(len(handles), 5), fontsize=7)
    _header(fig, "Stability under stress", runs)
    fig.tight_layout(rect=(0, 0.03, 1, 0.97))
    fig.savefig(path, dpi=110)
    return path
