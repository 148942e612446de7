"""Paper Table 5 on the bundled real TUM sample: full SEGS and its ablations, same budget.

Runs `python -m segs.train +experiment=sample slam=known_poses [+ablation=X] seed=S` for every
variant and seed (a finished run folder is reused and an interrupted one resumed from its
checkpoint, so the script can be interrupted and restarted), then writes the mean / std table
into docs/results.md between the markers <!-- sample-ablations:begin --> and
<!-- sample-ablations:end -->.

    python bench/sample_ablations.py --steps 3000 --seeds 0 1 2
"""
from __future__ import annotations

import argparse
import datetime
import json
import platform
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
VARIANTS = {
    "full SEGS": None,
    "w/o FPR": "no_fpr",
    "w/o AfME": "no_afme",
    "w/o FPR, AfME (SEPM only)": "no_fpr_afme",
    "w/o FPR, AfME, SEPM (plain 3D-GS)": "plain_3dgs",
}
PAPER_TUM_RGBD = {"full SEGS": 26.03, "w/o FPR": 25.04, "w/o AfME": 24.66, "w/o FPR, AfME (SEPM only)": 24.20,
                  "w/o FPR, AfME, SEPM (plain 3D-GS)": 21.73}  # fmt: skip
BEGIN, END = "<!-- sample-ablations:begin -->", "<!-- sample-ablations:end -->"


def run_one(ablation: str | None, seed: int, steps: int, out: Path, extra: list[str]) -> dict:
    metrics = out / "metrics.json"
    if metrics.exists():
        return json.loads(metrics.read_text())
    # an interrupted run resumes from its own checkpoint (segs.train refuses its folder otherwise)
    ckpt = next((p for p in (out / "checkpoints" / "final.ckpt", out / "checkpoints" / "last.ckpt") if p.is_file()), None)
    cmd = [sys.executable, "-m", "segs.train", "+experiment=sample", "slam=known_poses", f"seed={seed}",
           f"trainer.max_steps={steps}", f"hydra.run.dir={out}", "callbacks.slam_bridge.progress=false",
           "eval.progress=false", *extra] + ([f"+ablation={ablation}"] if ablation else []) + ([f"ckpt_path={ckpt}"] if ckpt else [])  # fmt: skip
    print(" ".join(cmd[1:]), flush=True)
    subprocess.run(cmd, check=True, cwd=ROOT)
    return json.loads(metrics.read_text())


def _cell(values: list[float], fmt: str) -> str:
    if any(v is None for v in values):
        return "n/a"
    a = np.asarray(values, float)
    return f"{a.mean():{fmt}} ± {a.std():{fmt}}" if len(a) > 1 else f"{a[0]:{fmt}}"


def table(results: dict[str, list[dict]], steps: int, seeds: list[int], extra: list[str]) -> str:
    cpu = next((line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name")), platform.processor())
    lines = [
        f"Measured {datetime.date.today()} on {cpu} (2 cores, no GPU), `python bench/sample_ablations.py --steps {steps} "
        f"--seeds {' '.join(map(str, seeds))}{' --extra ' + ' '.join(extra) if extra else ''}`: known (ground-truth) poses, "
        f"{steps} iterations at 320x240, {len(seeds)} seed(s) each (mean ± std over seeds), "
        f"{'/'.join(map(str, sorted({r['test_views'] for runs in results.values() for r in runs})))} test views (every 8th frame held out, "
        "plus the frames that did not become keyframes). Paper column: TUM RGB-D PSNR of Table 5 (fr1/desk, fr2/xyz, fr3/office, 30k iterations, GPU).",
        "",
        "| variant | test PSNR | test SSIM | anchors | Gaussians | MB | wall time (s) | paper TUM PSNR |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, runs in results.items():
        lines.append(
            f"| {name} | {_cell([r['psnr'] for r in runs], '.2f')} | {_cell([r['ssim'] for r in runs], '.3f')} | "
            f"{_cell([r['anchors'] for r in runs], '.0f')} | {_cell([r['gaussians'] for r in runs], '.0f')} | "
            f"{_cell([r['model_mb'] for r in runs], '.2f')} | {_cell([r['wall_time_s'] for r in runs], '.0f')} | "
            f"{PAPER_TUM_RGBD[name]:.2f} |"
        )
    return "\n".join(lines)


def write_section(text: str) -> None:
    path = ROOT / "docs" / "results.md"
    doc = path.read_text() if path.exists() else "# Results\n"
    block = f"{BEGIN}\n{text}\n{END}"
    if BEGIN in doc and END in doc:
        doc = doc[: doc.index(BEGIN)] + block + doc[doc.index(END) + len(END) :]
    else:
        doc = doc.rstrip() + "\n\n## Mapping ablations on the real TUM sample (paper Table 5)\n\n" + block + "\n"
    path.write_text(doc)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--steps", type=int, default=3000)
    p.add_argument("--seeds", type=int, nargs="+", default=[0])
    p.add_argument("--extra", nargs="*", default=[], help="more overrides for every run")
    p.add_argument("--out", type=Path, default=ROOT / "outputs" / "bench" / "sample_ablations")
    args = p.parse_args()
    results = {}
    for name, ablation in VARIANTS.items():
        tag = ablation or "full"
        results[name] = [run_one(ablation, s, args.steps, args.out / f"{tag}_steps{args.steps}_seed{s}", args.extra) for s in args.seeds]
    text = table(results, args.steps, args.seeds, args.extra)
    print(text)
    write_section(text)


if __name__ == "__main__":
    main()
