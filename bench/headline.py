"""The README's headline table, regenerated from run folders (never typed by hand).

    python bench/headline.py RUN_DIR [RUN_DIR ...]            # print the table
    python bench/headline.py RUN_DIR ... --write README.md     # and replace it between the markers

Each RUN_DIR is a finished `segs.train` run (metrics.json) or `segs.track` run (tracking.json);
its row is read from that file and its `provenance` record (segs.provenance): sequence, sensor,
frames tracked, ATE (n/a with the reason where the poses were not estimated), test-view PSNR /
SSIM, tracking frames/s, training iterations and seconds, model MB, the machine, the commit and
the command that made it (the run's command-line overrides). A folder without a finished result,
or whose result has no provenance record, is refused with one line naming it.
"""
from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

BEGIN, END = "<!-- headline:begin -->", "<!-- headline:end -->"
HEADER = ("| sequence | sensor | frames tracked | ATE | PSNR / SSIM (test views) | tracking frames/s | training | model MB | machine "
          "| commit | command |\n|---|---|---|---|---|---|---|---|---|---|---|")  # fmt: skip


def read_run(folder: Path) -> tuple[str, dict]:
    """("train" | "track", the result dict) of a finished run folder; SystemExit naming it otherwise."""
    for kind, name in (("train", "metrics.json"), ("track", "tracking.json")):
        path = folder / name
        if path.is_file():
            result = json.loads(path.read_text())
            if kind == "train" and result.get("status") != "finished":
                raise SystemExit(f"error: {path}: status {result.get('status')!r}, not a finished, evaluated run")
            if not result.get("provenance"):
                raise SystemExit(f"error: {path}: no provenance record (written before segs recorded one): run it again")
            return kind, result
    raise SystemExit(f"error: {folder}: neither metrics.json nor tracking.json (not a finished segs run)")


def _ate(r: dict) -> str:
    ate = r.get("ate") or {}
    if r.get("ate_rmse_m") is None:
        return f"n/a ({ate.get('reason', 'not measured')})"
    align = "Sim(3)" if ate.get("align") == "sim3" else "SE(3)" if ate.get("align") == "se3" else str(ate.get("align"))
    value = r["ate_rmse_m"]
    return f"{value * 100:.2f} cm ({align})" if value < 1.0 else f"{value:.2f} m ({align})"


def _portable(arg: str) -> str:
    """An override with machine-specific folders written as the README's commands write them:
    .../shared/data/X -> ../shared/data/X, .../datasets/X -> datasets/X."""
    arg = re.sub(r"=[^=\s]*/shared/data/", "=../shared/data/", arg)
    return re.sub(r"=/[^=\s]*/datasets/", "=datasets/", arg)


def _sequence(r: dict, overrides: list[str]) -> str:
    """The sequence's folder name (a reader's inner folder such as seq/ left out), with its frame range."""
    parts = Path(r.get("sequence") or "?").parts
    name = parts[-2] if len(parts) > 1 and parts[-1] in ("seq", "sequence") else parts[-1]
    frames = next((o.split("=", 1)[1] for o in overrides if o.startswith("data.frames=")), None)
    if frames:
        a, b = (int(x) for x in frames.strip("[]").split(","))
        name += f", frames {a}-{b - 1}"
    return name


def row(kind: str, r: dict) -> str:
    """One markdown row of the headline table."""
    p = r["provenance"]
    mach = p.get("machine") or {}
    commit = (p.get("git_commit") or "not a checkout")[:7] + (" (dirty)" if p.get("git_dirty") else "")
    overrides = [o for o in (p.get("overrides") or []) if not o.startswith(("task_name=", "hydra."))]
    command = " ".join([f"python -m segs.{kind}", *(_portable(o) for o in overrides)])
    fps = None if p.get("frontend") == "known_poses" else r.get("tracking_fps")
    if kind == "train":
        images = f"{r['psnr']:.2f} dB / {r['ssim']:.3f} ({r['test_views']})"
        training = f"{r['iterations']} it, {r['mapping_time_s']:.0f} s"
        mb = f"{r['model_mb']:.1f}"
    else:
        images, training, mb = "-", "- (tracking only)", "-"
    cells = [_sequence(r, overrides), p.get("sensor", "?"), f"{r['frames_tracked']}/{r['frames']}", _ate(r), images,
             "-" if fps is None else f"{fps:.1f}", training, mb, f"{mach.get('cpu', '?')}, {mach.get('cores', '?')} cores", commit,
             f"`{command}`"]  # fmt: skip
    return "| " + " | ".join(cells) + " |"


def table(folders: list[Path]) -> str:
    return "\n".join([HEADER, *(row(*read_run(f)) for f in folders)])


def write_between_markers(path: Path, text: str) -> None:
    """Replace what stands between the headline markers of path (both must be there)."""
    doc = path.read_text()
    pattern = re.compile(re.escape(BEGIN) + r".*?" + re.escape(END), re.S)
    if not pattern.search(doc):
        raise SystemExit(f"error: {path}: no {BEGIN} ... {END} markers")
    path.write_text(pattern.sub(lambda _: f"{BEGIN}\n{text}\n{END}", doc))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path, help="finished segs.train / segs.track run folders")
    ap.add_argument("--write", type=Path, default=None, help="a markdown file with the headline markers (README.md)")
    a = ap.parse_args(argv)
    text = table(a.runs)
    print(text)
    if a.write is not None:
        write_between_markers(a.write, text)
        print(f"-> {a.write}", file=sys.stderr)


if __name__ == "__main__":
    main()
