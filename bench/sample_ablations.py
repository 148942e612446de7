"""Paper Table 5 on real frames: full SEGS and its ablations, same budget.

Runs `python -m segs.train +experiment=E [+ablation=X] seed=S` for every variant and seed, seed
by seed (a finished run folder is reused and an interrupted one resumed from its checkpoint, so
the script can be interrupted and restarted), then writes the mean / std table into
docs/results.md between the markers <!-- E-ablations:begin --> and <!-- E-ablations:end -->.

    python bench/sample_ablations.py --steps 3000 --seeds 0 1 2
        (the bundled TUM sample, ground-truth poses: slam=known_poses)
    python bench/sample_ablations.py --experiment seven_scenes_rgbd --steps 3000 --seeds 0 1 2 \
        --extra data.downscale=2
        (the shared 600 7-Scenes frames with the ORB frontend in the loop, the paper's split)
"""
from __future__ import annotations

import argparse
import datetime
import json
import subprocess
import sys
from pathlib import Path

import _harness

_harness.apply_process_settings()  # before torch loads

import numpy as np

ROOT = _harness.ROOT
VARIANTS = {
    "full SEGS": None,
    "w/o FPR": "no_fpr",
    "w/o AfME": "no_afme",
    "w/o FPR, AfME (SEPM only)": "no_fpr_afme",
    "w/o FPR, AfME, SEPM (plain 3D-GS)": "plain_3dgs",
}
PAPER_TUM_RGBD = {"full SEGS": 26.03, "w/o FPR": 25.04, "w/o AfME": 24.66, "w/o FPR, AfME (SEPM only)": 24.20,
                  "w/o FPR, AfME, SEPM (plain 3D-GS)": 21.73}  # fmt: skip
TITLES = {"sample": "Mapping ablations on the real TUM sample (paper Table 5)",
          "seven_scenes_rgbd": "Mapping ablations on the 7-Scenes frames with the ORB frontend (paper Table 5)"}


def markers(experiment: str) -> tuple[str, str]:
    return f"<!-- {experiment}-ablations:begin -->", f"<!-- {experiment}-ablations:end -->"


def run_one(experiment: str, ablation: str | None, seed: int, steps: int, out: Path, extra: list[str]) -> dict:
    metrics = out / "metrics.json"
    if metrics.exists():
        return json.loads(metrics.read_text())
    # an interrupted run resumes from its own checkpoint (segs.train refuses its folder otherwise)
    ckpt = next((p for p in (out / "checkpoints" / "final.ckpt", out / "checkpoints" / "last.ckpt") if p.is_file()), None)
    frontend = ["slam=known_poses"] if experiment == "sample" else []  # the sample's frames are 0.15 m apart
    data = [f"data.root={_harness.SEVEN_SCENES}"] if experiment.startswith("seven_scenes") else []
    cmd = [sys.executable, "-m", "segs.train", f"+experiment={experiment}", *frontend, *data, f"seed={seed}",
           f"trainer.max_steps={steps}", f"hydra.run.dir={out}", "callbacks.slam_bridge.progress=false",
           "eval.progress=false", *extra] + ([f"+ablation={ablation}"] if ablation else []) + ([f"ckpt_path={ckpt}"] if ckpt else [])  # fmt: skip
    print(" ".join(cmd[1:]), flush=True)
    subprocess.run(cmd, check=True, cwd=ROOT)
    return json.loads(metrics.read_text())


def _cell(values: list[float], fmt: str) -> str:
    if any(v is None for v in values):
        return "n/a"
    a = np.asarray(values, float)
    return f"{a.mean():{fmt}} ± {a.std():{fmt.lstrip('+')}}" if len(a) > 1 else f"{a[0]:{fmt}}"


def table(results: dict[str, list[dict]], experiment: str, steps: int, seeds: list[int], extra: list[str]) -> str:
    machine = _harness.record()["machine"]
    runs = [r for rs in results.values() for r in rs]
    views = "/".join(map(str, sorted({r["test_views"] for r in runs})))
    cmd = (f"python bench/sample_ablations.py{'' if experiment == 'sample' else ' --experiment ' + experiment} --steps {steps} "
           f"--seeds {' '.join(map(str, seeds))}{' --extra ' + ' '.join(extra) if extra else ''}")
    how = ("known (ground-truth) poses, every 8th frame held out plus the frames that did not become keyframes" if experiment == "sample"
           else "the ORB frontend in the loop (slam=orb), keyframes train and every other tracked frame is a test view rendered at its estimated pose")  # fmt: skip
    lines = [
        f"Measured {datetime.date.today()} on {machine['cpu']} ({machine['cores']} cores, no GPU), `{cmd}`: {how}; {steps} iterations, "
        f"{len(seeds)} seed(s) each (mean ± std over seeds), {views} test views. Paper column: TUM RGB-D PSNR of Table 5 "
        "(fr1/desk, fr2/xyz, fr3/office, 30k iterations, GPU).",
        "",
    ]
    lossless = all(r.get("lossless_views") for r in runs)
    tracked = experiment != "sample"
    full = results["full SEGS"]
    head = ["variant", "test PSNR", "PSNR - full (same seed)", "test SSIM"] + (["PSNR vs lossless (same views vs JPEG)"] if lossless else []) + (
        ["ATE (cm)", "tracked"] if tracked else []) + ["anchors", "Gaussians", "MB", "mapping time (s)", "paper TUM PSNR"]
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, rs in results.items():
        paired = [r["psnr"] - f["psnr"] for r, f in zip(rs, full)]  # seeds in the same order
        cells = [name, _cell([r["psnr"] for r in rs], ".2f"), "-" if rs is full else _cell(paired, "+.2f"), _cell([r["ssim"] for r in rs], ".3f")]
        if lossless:
            cells.append(f"{_cell([r['psnr_lossless'] for r in rs], '.2f')} ({_cell([r['psnr_jpeg_on_lossless_views'] for r in rs], '.2f')})")
        if tracked:
            cells += [_cell([r["ate_rmse_m"] and r["ate_rmse_m"] * 100 for r in rs], ".2f"),
                      f"{min(r['frames_tracked'] for r in rs)}/{rs[0]['frames']}"]
        cells += [_cell([r["anchors"] for r in rs], ".0f"), _cell([r["gaussians"] for r in rs], ".0f"),
                  _cell([r["model_mb"] for r in rs], ".2f"), _cell([r["mapping_time_s"] for r in rs], ".0f"), f"{PAPER_TUM_RGBD[name]:.2f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def write_section(text: str, experiment: str) -> None:
    path = ROOT / "docs" / "results.md"
    doc = path.read_text() if path.exists() else "# Results\n"
    begin, end = markers(experiment)
    block = f"{begin}\n{text}\n{end}"
    if begin in doc and end in doc:
        doc = doc[: doc.index(begin)] + block + doc[doc.index(end) + len(end) :]
    else:
        doc = doc.rstrip() + f"\n\n## {TITLES.get(experiment, experiment + ' ablations')}\n\n" + block + "\n"
    path.write_text(doc)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--experiment", default="sample", help="conf/experiment/<name>.yaml")
    p.add_argument("--steps", type=int, default=3000)
    p.add_argument("--seeds", type=int, nargs="+", default=[0])
    p.add_argument("--extra", nargs="*", default=[], help="more overrides for every run")
    p.add_argument("--out", type=Path, default=None, help="default: outputs/bench/<experiment>_ablations")
    args = p.parse_args()
    out = args.out or _harness.OUTPUTS / ("sample_ablations" if args.experiment == "sample" else f"{args.experiment}_ablations")
    results = {name: [] for name in VARIANTS}
    for s in args.seeds:  # seed by seed: an interrupted sweep leaves whole seeds
        for name, ablation in VARIANTS.items():
            tag = ablation or "full"
            results[name].append(run_one(args.experiment, ablation, s, args.steps, out / f"{tag}_steps{args.steps}_seed{s}", args.extra))
    text = table(results, args.experiment, args.steps, args.seeds, args.extra)
    print(text)
    write_section(text, args.experiment)


if __name__ == "__main__":
    main()
