"""Side by side with the CPU peer OpenSplat: test-view PSNR / SSIM against wall seconds, one script.

    python bench/peers.py --opensplat PATH [--datasets sample 7scenes] [--budgets MIN ...] [--repeats N] [--write docs/performance.md]
    python bench/peers.py --report outputs/bench/peers.json [--write docs/performance.md]   # table and chart again
    python bench/peers.py --report A.json B.json ...   # several runs' JSONs in one table (a later run's budget supersedes)

Both methods get the same training views, poses, initial points and test views, and both are
scored by one function with the project's PSNR / SSIM (segs.modules.metrics) on the full frames.
For every dataset the views are exported once (a 1-step segs run built as bench/time_to_quality.py
builds one, every frame fed before the first step: the training views it trains on, the test
views it holds out, the frontend's poses, the SLAM points its mapper receives), then for every
budget (minutes, ascending) one OpenSplat run and one segs run, in alternating order:
- OpenSplat (the binary given, its default schedule, `--keep-crs`) on the views cropped so that
  the principal point is centred (its CPU path ignores cx, cy); `-n` sized to end at the budget
  from the step rates of the earlier runs (a 100-step pilot first), or between two runs of the
  budget that ended either side of it (its pace depends on -n: it densifies until n / 2); its
  time is measured from launch to its last step; snapshots (`--save-every`) give the chart's
  intermediate points.
  Scored with `render_native` (what its own renderer draws; bench/_opensplat.py) and also with a
  correct 3D-GS renderer of its PLY ("std.").
- segs with the defaults of the dataset's experiment, `trainer.max_steps` sized to end at the
  budget (a 200-step pilot first, then the rate of the latest run, for a longer budget with its
  fall from the run before carried on: segs_rate_trend), in a child process
  timed from its launch; the clock stops while test views are scored (at the smaller budgets, for
  the chart, and at the end), and the run stops at the budget. Where the size is under the
  schedules' floor (a coarse-to-fine run shorter than mapping.min_schedule_steps, as at 1 and 2
  minutes on the sample), the run is given the floor's steps and the budget stops it: its
  schedules are the floor's whatever its max_steps, so the run stopped at step n is the run sized
  to n steps, and it uses the whole budget instead of an estimate's share of it (segs_max_steps,
  fits). Elsewhere a run that ends outside its budget is sized again (fits).
Each program runs under /usr/bin/time -v (peak RSS, CPU %), with OMP_NUM_THREADS=2 and its own
OpenMP wait policy (OpenSplat: libgomp's default; segs: decision 033's, chosen as it starts;
OMP_WAIT_POLICY / GOMP_SPINCOUNT are removed from their environment). Before the budgets, `render_native` is checked against OpenSplat's own
`--val-render` image of a training view (60 full-size steps): the PSNR between them is recorded.

With --repeats N every budget runs N times (both methods, the order alternated); the table gives
each method's median run (by final PSNR; its seconds, steps and size), the lowest and highest PSNR
of the N runs in brackets, the highest peak RSS, and the difference of the medians.

Output: outputs/bench/peers.json (every run and point; a point's "views": each test view's PSNR,
which `--report JSON ... --views` lists for the median runs), docs/performance/peers.png (PSNR against
wall seconds), the markdown tables on stdout and, with --write, between the markers
<!-- peers:begin --> and <!-- peers:end --> of that file.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import _harness

_harness.apply_process_settings()  # before numpy / torch load

import numpy as np

ROOT = _harness.ROOT
sys.path.insert(0, str(Path(__file__).resolve().parent))
import _opensplat as peer  # noqa: E402
from _pacing import PILOT_RATE_FACTOR, TRIES, fits, peer_iterations, segs_max_steps  # noqa: E402

SEVEN_SCENES = _harness.SEVEN_SCENES
BEGIN, END = "<!-- peers:begin -->", "<!-- peers:end -->"
THREADS_ENV = {"OMP_NUM_THREADS": "2", "MKL_NUM_THREADS": "2"}
WAIT_VARS = ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")  # each program keeps its own default
PEER_PILOT_ITERS, SEGS_PILOT_STEPS = 100, 200
EXPORT_KEYS = ("train_views", "test_views", "points", "crop")  # what runs joined by --report must share
PEER_SNAPSHOTS = 5  # --save-every = iterations // this (chart points)


@dataclass(frozen=True)
class Dataset:
    """overrides: the segs run (time_to_quality's QUIET and feed-all are added); budgets: minutes
    run by default; test_stride: every n-th of the run's test views is scored (both methods)."""

    overrides: tuple[str, ...]
    budgets: tuple[float, ...]
    test_stride: int
    note: str


DATASETS = {
    "sample": Dataset(("+experiment=sample",), (1, 2, 4, 8, 15), 1,
                      "the bundled TUM fr3/cabinet sample, 320x240, known poses"),
    "7scenes": Dataset(("+experiment=seven_scenes_rgbd", "slam=known_poses", f"data.root={SEVEN_SCENES}", "data.frames=[100,250]",
                        "eval.holdout_every=8"), (2, 8), 4,
                       "7-Scenes redkitchen frames 100-249, 640x480, known poses, every 8th frame held out"),
}  # fmt: skip


def _ttq():
    import time_to_quality

    return time_to_quality


# -- export ---------------------------------------------------------------------------------------
def export(name: str, work: Path, seed: int) -> dict:
    """The dataset's split for both methods, and OpenSplat's input folder (work/NAME/input).

    Returns the split: {"dataset", "overrides", "train", "test", "camera", "crop", "w2c" (frame ->
    [4,4]), "points", "frame" (OpenSplat's normalisation), "input"}."""
    import torch

    from segs.modules.contract import to_uint8

    ds = DATASETS[name]
    overrides = list(ds.overrides) + [f"seed={seed}"]
    pts, cols = [], []
    cfg, sequence, module, bridge, trainer = _harness.build_training(overrides, 1, Path(tempfile.mkdtemp(prefix="export_", dir=work)), [])
    add_points = module.add_points

    def recording(xyz, rgb, kf_ids):
        pts.append(xyz.detach().cpu().numpy().copy())
        cols.append(rgb.detach().cpu().numpy().copy())
        return add_points(xyz, rgb, kf_ids)

    module.add_points = recording
    _harness.fit(cfg, module, trainer)
    trajectory = bridge.run.trajectory()
    train, test = sorted(bridge.run.trained_frames().values()), bridge.run.test_frames()[:: ds.test_stride]
    c = sequence.camera
    camera = {"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy, "width": c.width, "height": c.height}
    crop = peer.principal_point_crop(c.cx, c.cy, c.width, c.height)
    views = [(i, to_uint8(torch.from_numpy(np.ascontiguousarray(sequence[i].rgb))).numpy(), trajectory[i]) for i in train]
    xyz, rgb = np.concatenate(pts).astype(np.float32), np.concatenate(cols).astype(np.float32)
    folder = work / name / "input"
    frame = peer.write_input(folder, camera, crop, views, xyz, rgb)
    split = {"dataset": name, "overrides": overrides, "train": train, "test": test, "camera": camera, "crop": crop.__dict__,
             "w2c": {str(i): np.asarray(trajectory[i], np.float64).tolist() for i in train + test}, "points": len(xyz),
             "frame": frame, "input": str(folder)}  # fmt: skip
    (work / name / "split.json").write_text(json.dumps(split))
    return split


def view_source(split: dict):
    """(sequence, trajectory) of the split's dataset, for scoring in this process."""
    from segs.config import compose, make_sequence

    cfg = compose(split["overrides"], output_dir=tempfile.mkdtemp(prefix="peers_score_"))
    return make_sequence(cfg.data), {int(k): np.asarray(v) for k, v in split["w2c"].items()}


def score_views(render, sequence, trajectory: dict, test: list[int], crop: dict) -> dict:
    """Mean PSNR / SSIM (segs.modules.metrics) of render(w2c [4,4], camera) -> [H,W,3] over the test
    views, on the full frames and on the region OpenSplat trains on (the crop); "views": each test
    view's full-frame PSNR, keyed by its frame number (a string, as JSON keeps it)."""
    import torch

    from segs.modules.metrics import psnr, ssim

    rows = []
    for idx in test:
        frame = sequence[idx]
        gt = torch.from_numpy(np.ascontiguousarray(frame.rgb))
        image = render(trajectory[idx], frame.camera)
        h, w = gt.shape[:2]
        cut = (slice(crop["top"], h - crop["bottom"]), slice(crop["left"], w - crop["right"]))
        rows.append((psnr(image, gt), ssim(image, gt), psnr(image[cut], gt[cut]), ssim(image[cut], gt[cut])))
    m = np.mean(rows, axis=0)
    return {"psnr": float(m[0]), "ssim": float(m[1]), "psnr_crop": float(m[2]), "ssim_crop": float(m[3]), "test_views": len(rows),
            "views": {str(idx): float(r[0]) for idx, r in zip(test, rows)}}  # fmt: skip


def _camera_dict(camera) -> dict:
    return {"fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy, "width": camera.width, "height": camera.height}


def score_peer(ply: str, split: dict, source, standard: bool = True) -> dict:
    """OpenSplat's PLY on the test views: its own renderer (psnr, ssim, ...) and, with standard,
    a correct 3D-GS renderer (psnr_std, ssim_std); its Gaussians and model MB."""
    model = peer.PeerModel(ply, split["frame"])
    sequence, trajectory = source
    out = score_views(lambda w2c, cam: model.render_native(w2c, _camera_dict(cam)), sequence, trajectory, split["test"], split["crop"])
    if standard:
        std = score_views(lambda w2c, cam: model.render_standard(w2c, _camera_dict(cam)), sequence, trajectory, split["test"],
                          split["crop"])  # fmt: skip
        out.update(psnr_std=std["psnr"], ssim_std=std["ssim"])
    active = int((model.opacities > 0.005).sum())
    return {**out, "step": model.step, "gaussians": model.n, "active": active, "model_mb": model.model_mb(),
            "non_finite": model.non_finite}


def check_renderer(binary: str, split: dict, work: Path) -> float:
    """PSNR between render_native and OpenSplat's own --val-render image of its first training
    view, after 60 full-size steps (the camera it trains with: cropped, principal point centred)."""
    import cv2
    import torch

    from segs.modules.metrics import psnr

    out = work / "renderer_check"
    (out / "val").mkdir(parents=True, exist_ok=True)
    first = split["train"][0]
    cmd = [binary, split["input"], "-n", "60", "--num-downscales", "0", "--keep-crs", "-o", str(out / "splat.ply"),
           "--val-render", str(out / "val"), "--val-image", f"{first:05d}.png"]  # fmt: skip
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT, env=child_env())
    theirs = cv2.cvtColor(cv2.imread(str(out / "val" / "60.png")), cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0
    h, w = theirs.shape[:2]
    cam = {"fx": split["camera"]["fx"], "fy": split["camera"]["fy"], "cx": (w - 1) / 2, "cy": (h - 1) / 2, "width": w, "height": h}
    ours = peer.PeerModel(out / "splat.ply", split["frame"]).render_native(np.asarray(split["w2c"][str(first)]), cam)
    return psnr(ours, torch.from_numpy(theirs))


# -- runs -----------------------------------------------------------------------------------------
def child_env() -> dict:
    """The environment of both methods' processes: two threads each, no wait policy of this script's."""
    return {**{k: v for k, v in os.environ.items() if k not in WAIT_VARS}, **THREADS_ENV}


def run_peer(binary: str, split: dict, budget_s: float, runs: list[dict], out: Path, source) -> dict:
    """One OpenSplat run sized for budget_s, scored (final PLY and snapshots)."""
    n = peer_iterations(budget_s, runs, PILOT_RATE_FACTOR if len(runs) == 1 else 1.0)
    res = peer.run(binary, Path(split["input"]), n, out, child_env(), save_every=max(n // PEER_SNAPSHOTS, 1))
    points = []
    for step, ply in sorted(res["snapshots"].items()):
        points.append({"seconds": peer.seconds_at(res["steps"], step), "steps": step, **score_peer(ply, split, source, False)})
        Path(ply).unlink()
    final = score_peer(res["ply"], split, source)
    points.append({"seconds": res["wall_s"], "steps": n, **final})
    return {"method": "opensplat", "budget_s": budget_s, **{k: v for k, v in res.items() if k != "snapshots"}, "points": points}


def run_segs(split_path: Path, budget_s: float, max_steps: int, marks: list[float], out: Path) -> dict:
    """One segs run (a child process under /usr/bin/time -v)."""
    out.mkdir(parents=True, exist_ok=True)
    part = out / "part.json"
    cmd = ["/usr/bin/time", "-v", "-o", str(out / "time.txt"), sys.executable, __file__, "--segs-run", str(split_path),
           "--budget-s", str(budget_s), "--max-steps", str(max_steps), "--launch", str(time.time()), "--part", str(part),
           "--marks", *[str(m) for m in marks]]  # fmt: skip
    with open(out / "log.txt", "w") as log:
        subprocess.run(cmd, check=True, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT, env=child_env())
    return {"method": "segs", **json.loads(part.read_text()), **peer.gnu_time(out / "time.txt")}


def segs_child(args) -> None:
    """--segs-run SPLIT: train with the clock started at the parent's launch time, score at marks."""
    launch = args.launch
    ttq = _ttq()
    split = json.loads(Path(args.segs_run).read_text())
    out = Path(args.part).parent
    clock = ttq.TrainingClock(args.marks, args.budget_s, lambda m: {})
    cfg, sequence, module, bridge, trainer = _harness.build_training(split["overrides"], args.max_steps, out / "run", [clock])
    trajectory = {int(k): np.asarray(v) for k, v in split["w2c"].items()}

    def score(m) -> dict:
        if sorted(bridge.run.trained_frames().values()) != split["train"] or not set(split["test"]) <= set(bridge.run.test_frames()):
            raise RuntimeError("the run's training / test views are not the exported split's")
        res = score_views(lambda w2c, cam: m.render_image(w2c, cam)["image"], sequence, trajectory, split["test"], split["crop"])
        c = m.counts()
        active = np.mean([m.count_active(trajectory[i], sequence.camera, 0.005) for i in split["test"]])
        return {**res, "anchors": c.anchors, "gaussians": c.gaussians, "active": float(active), "model_mb": c.mb}

    clock.score = score
    clock.seconds = time.time() - launch  # imports and building count: the clock runs from launch
    clock.start()
    _harness.fit(cfg, module, trainer)
    clock.stop()
    Path(args.part).write_text(json.dumps({
        "budget_s": args.budget_s, "max_steps": args.max_steps, "steps": int(trainer.global_step), "startup_s": clock.first_step_s,
        "train_s": clock.seconds, "eval_s": sum(p["eval_s"] for p in clock.points), "points": clock.points,
        "schedule_done": trainer.global_step / args.max_steps, "scheduled_steps": int(module.model.total_steps),
        "schedule_floor": int(cfg.mapping.min_schedule_steps) if cfg.mapping.num_downscales > 0 else 0,
        "omp": {k: os.environ.get(k) for k in WAIT_VARS}}))  # fmt: skip


def run_dataset(name: str, binary: str, budgets: list[float], work: Path, seed: int, record: dict, save, tries: int = TRIES,
                repeats: int = 1) -> None:  # fmt: skip
    """Export, check the renderer, pilots, then every budget `repeats` times: OpenSplat and segs
    alternately (the order swapped from one budget or repeat to the next), each run sized from
    the latest run of its method."""
    split = export(name, work, seed)
    split_path = work / name / "split.json"
    source = view_source(split)
    entry = {"dataset": name, "note": DATASETS[name].note, "train_views": len(split["train"]), "test_views": len(split["test"]),
             "points": split["points"], "crop": split["crop"], "renderer_check_db": check_renderer(binary, split, work / name),
             "runs": []}  # fmt: skip
    record["datasets"].append(entry)
    print(f"peers: {name}: {entry['train_views']} training / {entry['test_views']} test views, {split['points']} points; "
          f"render_native vs OpenSplat's --val-render {entry['renderer_check_db']:.1f} dB", flush=True)
    peer_runs = [peer.run(binary, Path(split["input"]), PEER_PILOT_ITERS, work / name / "opensplat_pilot", child_env())]
    segs_runs = [run_segs(split_path, 600.0, SEGS_PILOT_STEPS, [], work / name / "segs_pilot")]
    for i, minutes in enumerate(sorted(budgets)):
        b = minutes * 60.0
        marks = [m * 60.0 for m in budgets if m < minutes]
        for rep in range(repeats):
            for method in ("opensplat", "segs") if (i + rep) % 2 == 0 else ("segs", "opensplat"):
                runs = peer_runs if method == "opensplat" else segs_runs
                for attempt in range(tries):
                    out = work / name / f"{method}_{minutes:g}min_{'' if rep == 0 else f'r{rep}_'}{attempt}"
                    if method == "opensplat":
                        r = run_peer(binary, split, b, runs, out, source)
                    else:
                        steps = segs_max_steps(b, runs, PILOT_RATE_FACTOR if len(runs) == 1 else 1.0)
                        r = run_segs(split_path, b, steps, marks, out)
                    runs.append(r)
                    r["attempt"], r["repeat"] = attempt, rep
                    entry["runs"].append({"budget_min": minutes, **r})
                    last = r["points"][-1]
                    print(f"peers: {name} {minutes:g} min {method} (repeat {rep + 1} of {repeats}): {last['psnr']:.2f} dB / "
                          f"{last['ssim']:.3f} at {last['seconds']:.0f} s, {last['steps']} steps, {last['gaussians']} Gaussians, "
                          f"peak RSS {r['peak_rss_mb']:.0f} MB", flush=True)
                    save()
                    if fits(r, b):
                        break


# -- report ---------------------------------------------------------------------------------------
def _finals(entry: dict, method: str, minutes: float) -> list[dict]:
    """A method's runs at a budget that the table counts: of the latest record that ran it (runs
    merged from several records carry their "part"), the last attempt of each repeat."""
    runs = [r for r in entry["runs"] if r["method"] == method and r["budget_min"] == minutes]
    if not runs:
        return []
    part = max(r.get("part", 0) for r in runs)
    last = {r.get("repeat", 0): r for r in runs if r.get("part", 0) == part}
    return [last[k] for k in sorted(last)]


def _median(runs: list[dict]) -> dict | None:
    """The run of median final PSNR (the lower one of an even count)."""
    runs = sorted(runs, key=lambda r: r["points"][-1]["psnr"])
    return runs[(len(runs) - 1) // 2] if runs else None


def _final(entry: dict, method: str, minutes: float) -> dict | None:
    """The run of median final PSNR among `_finals`."""
    return _median(_finals(entry, method, minutes))


def _spread(runs: list[dict]) -> str:
    """' [lowest-highest PSNR, n runs]' of a repeated budget's runs, else ''."""
    psnr = [r["points"][-1]["psnr"] for r in runs]
    return f" [{min(psnr):.2f}-{max(psnr):.2f}, {len(psnr)} runs]" if len(psnr) > 1 else ""


def view_rows(entry: dict) -> list[str]:
    """Markdown rows of each budget's test views: the median runs' final PSNR per view, both methods
    and the difference (records from 4466f93 on; older runs kept no per-view figures)."""
    out = []
    for minutes in _budgets(entry):
        p, s = _final(entry, "opensplat", minutes), _final(entry, "segs", minutes)
        pv, sv = (r["points"][-1].get("views") if r else None for r in (p, s))
        if not pv or not sv:
            out.append(f"| {entry['dataset']}, {minutes:g} min | no per-view figures in this record | | |")
            continue
        for view in sorted(set(pv) & set(sv), key=int):
            theirs, ours = pv[view], sv[view]
            out.append(f"| {entry['dataset']}, {minutes:g} min, view {view} | {theirs:.2f} | {ours:.2f} | {ours - theirs:+.2f} |")
    return out


def views_report(record: dict) -> str:
    """--views: the per-view table of every dataset and budget of a record."""
    head = ["| data, budget, test view | OpenSplat PSNR | segs PSNR | segs - OpenSplat dB |", "|---|---|---|---|"]
    return "\n".join(head + [row for e in record["datasets"] for row in view_rows(e)])


def _budgets(entry: dict) -> list[float]:
    return sorted({r["budget_min"] for r in entry["runs"]})


def _miss(run: dict) -> str:
    """' *' when the run's time or schedule missed its budget after every try (fits)."""
    return "" if fits(run, run["budget_s"]) else " *"


def _k(n: float) -> str:
    return f"{n / 1000:.1f}k" if n >= 1000 else f"{n:.0f}"


def rows(entry: dict) -> list[str]:
    """Markdown rows, one per budget: both methods' PSNR / SSIM, seconds, steps, size, peak RSS."""
    out = []
    for minutes in _budgets(entry):
        ps, ss = _finals(entry, "opensplat", minutes), _finals(entry, "segs", minutes)
        p, s = _median(ps), _median(ss)
        cells = [f"{entry['dataset']}, {minutes:g} min"]
        if p:
            q = p["points"][-1]
            cells += [f"{q['psnr']:.2f}{_spread(ps)} / {q['ssim']:.3f} ({q['psnr_std']:.2f})",
                      f"{q['seconds']:.0f}{_miss(p)}, {q['steps']:,}", f"{_k(q['gaussians'])}, {q['model_mb']:.1f}",
                      f"{max(r['peak_rss_mb'] for r in ps):.0f}"]  # fmt: skip
        else:
            cells += ["-"] * 4
        if s:
            q, schedule = s["points"][-1], s.get("scheduled_steps", s["max_steps"])
            cells += [f"{q['psnr']:.2f}{_spread(ss)} / {q['ssim']:.3f}",
                      f"{q['seconds']:.0f}{_miss(s)}, {q['steps']:,} ({schedule:,})",
                      f"{_k(q['anchors'])}, {_k(q['gaussians'])} ({_k(q['active'])}), {q['model_mb']:.1f}",
                      f"{max(r['peak_rss_mb'] for r in ss):.0f}"]
        else:
            cells += ["-"] * 4
        cells.append(f"**{s['points'][-1]['psnr'] - p['points'][-1]['psnr']:+.2f}**" if p and s else "-")
        out.append("| " + " | ".join(cells) + " |")
    return out


def merge(records: list[dict]) -> dict:
    """One record from the JSONs of several runs of this script, in order: each dataset's runs
    appended, so that a later record's runs at a budget supersede an earlier one's (`_finals`); every
    run's command and machine kept ("parts") for the report's head. A dataset exported differently
    in two of them (views, initial points) cannot share a table: SystemExit naming it."""
    parts, datasets = [], {}
    for rec in records:
        offset = len(parts)
        parts += rec.get("parts") or [{"command": rec["command"], "machine": rec["machine"]}]
        for e in rec["datasets"]:
            first = datasets.setdefault(e["dataset"], {**e, "runs": []})
            if any(first.get(k) != e.get(k) for k in EXPORT_KEYS):
                raise SystemExit(f"error: dataset {e['dataset']!r} differs between the merged records ({', '.join(EXPORT_KEYS)})")
            first["runs"] += [{**r, "part": offset + r.get("part", 0)} for r in e["runs"]]
    return {"parts": parts, "machine": parts[-1]["machine"], "command": "; ".join(p["command"] for p in parts),
            "datasets": list(datasets.values())}


def _part_head(part: dict) -> str:
    """`command` (commit, date; machine; OpenSplat version; load) of one run of this script."""
    m, command = part["machine"], re.sub(r" --(chart|work) \S+", "", part["command"])
    return (f"`{command}` (commit {m['commit']}, {m['date']}; {m['cpu']}, {m['cores']} cores; OpenSplat {m['opensplat']}; "
            f"load average before {m['load_before']}, after {m.get('load_after', '-')})")


def report(record: dict) -> str:
    """The machines and commands, each dataset's views and renderer check, and one table."""
    entries = record["datasets"]
    parts = record.get("parts") or [{"command": record["command"], "machine": record["machine"]}]
    head = ("; ".join(_part_head(p) for p in parts) + ". "
            + "; ".join(f"{e['dataset']}: {e['train_views']} training / {e['test_views']} test views, {e['points']:,} initial points, "
                        f"render_native against its --val-render {e['renderer_check_db']:.1f} dB" for e in entries) + ".")
    table = ["| data, budget | OpenSplat PSNR / SSIM (std.) | s, iterations | Gaussians, MB | peak RSS MB | segs PSNR / SSIM | "
             "s, steps (schedule) | anchors, Gaussians (active), MB | peak RSS MB | segs - OpenSplat dB |", "|" + "---|" * 10]
    table += [row for e in entries for row in rows(e)]
    note = ("s: wall seconds from launch; * outside -15 / +8 % of the budget (segs: or stopped before its steps' end) after "
            "the tries; (schedule): the steps segs's schedules are sized for (model.total_steps: the run's steps, or "
            "mapping.min_schedule_steps when more; records without it give the run's steps); "
            "std.: a correct 3D-GS render of OpenSplat's PLY; active: drawn with opacity > 0.005, mean over the test views; "
            "[a-b, n runs]: a repeated budget's lowest and highest PSNR, the cells beside it the median run's, peak RSS the highest, "
            "the difference the medians'.")
    return "\n".join([head, "", *table, "", note])


def chart(record: dict, path: Path) -> None:
    """PSNR against wall seconds from launch, one panel per dataset: each budget's run (line) and
    the intermediate points (segs: scored at the smaller budgets; OpenSplat: its snapshots)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    entries = record["datasets"]
    fig, axes = plt.subplots(1, len(entries), figsize=(4.6 * len(entries), 3.4), squeeze=False)
    for ax, e in zip(axes[0], entries):
        for method, colour in (("opensplat", "tab:orange"), ("segs", "tab:blue")):
            runs = [r for r in (_final(e, method, m) for m in _budgets(e)) if r]
            finals = [r["points"][-1] for r in runs]
            ax.plot([p["seconds"] for p in finals], [p["psnr"] for p in finals], "o-", color=colour, ms=4, label=method)
            inner = [p for r in runs for p in r["points"][:-1]]
            ax.plot([p["seconds"] for p in inner], [p["psnr"] for p in inner], "x", color=colour, ms=4, alpha=0.6)
        ax.set_xscale("log")
        ticks = [m * 60 for m in _budgets(e)]
        ax.set_xticks(ticks, [f"{t / 60:g} min" for t in ticks], fontsize=7)
        ax.minorticks_off()
        ax.set_title(f"{e['dataset']} ({e['test_views']} test views)", fontsize=10)
        ax.set_xlabel("wall seconds from launch (scoring excluded)", fontsize=8)
        ax.set_ylabel("test-view PSNR (dB)", fontsize=8)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def write_between_markers(path: Path, text: str) -> None:
    """Replace what stands between the peers markers of path (both must be there)."""
    doc = path.read_text()
    if BEGIN not in doc or END not in doc:
        raise SystemExit(f"error: {path}: no {BEGIN} ... {END} markers")
    head, rest = doc.split(BEGIN, 1)
    path.write_text(head + BEGIN + "\n" + text + "\n" + END + rest.split(END, 1)[1])


def machine(binary: str | None) -> dict:
    """CPU, cores, commit, date, load (_harness.record()) and the OpenSplat version."""
    rec = _harness.record()
    version = subprocess.run([binary, "--version"], capture_output=True, text=True).stdout.strip() if binary else "-"
    commit = (rec["code"].get("commit") or "-")[:7] + (" (dirty)" if rec["code"].get("dirty") else "")
    return {"cpu": rec["machine"]["cpu"], "cores": rec["machine"]["cores"], "commit": commit, "date": rec["time"][:10],
            "load_before": _load(), "opensplat": version}  # fmt: skip


def _load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--opensplat", default=os.environ.get("OPENSPLAT"), help="the OpenSplat binary (default: $OPENSPLAT)")
    p.add_argument("--datasets", nargs="+", default=list(DATASETS), choices=list(DATASETS))
    p.add_argument("--budgets", type=float, nargs="+", default=None, help="minutes (default: each dataset's)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--tries", type=int, default=TRIES, help="runs per method and budget at most (a run missing its budget is sized again)")
    p.add_argument("--repeats", type=int, default=1, help="runs of each method at each budget (the table: the median run, the range)")
    p.add_argument("--work", type=Path, default=ROOT / "outputs" / "bench" / "peers")
    p.add_argument("--out", type=Path, default=ROOT / "outputs" / "bench" / "peers.json")
    p.add_argument("--chart", type=Path, default=ROOT / "docs" / "performance" / "peers.png")
    p.add_argument("--write", type=Path, default=None, help="a markdown file with the peers markers (docs/performance.md)")
    p.add_argument("--report", type=Path, nargs="+", default=None,
                   help="only print the tables and redraw the chart of these output JSONs (merged in order)")
    p.add_argument("--views", action="store_true", help="with --report: print each test view's PSNR (the median runs) instead")
    p.add_argument("--segs-run", help=argparse.SUPPRESS)
    for hidden in ("--budget-s", "--launch"):
        p.add_argument(hidden, type=float, help=argparse.SUPPRESS)
    p.add_argument("--max-steps", type=int, help=argparse.SUPPRESS)
    p.add_argument("--part", help=argparse.SUPPRESS)
    p.add_argument("--marks", type=float, nargs="*", default=[], help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.repeats < 1:
        raise SystemExit(f"error: --repeats must be at least 1, got {args.repeats}")
    if args.segs_run:
        return segs_child(args)
    if args.report:
        missing = [str(p) for p in args.report if not p.is_file()]
        if missing:
            raise SystemExit(f"error: no such report JSON: {missing[0]}")
        record = merge([json.loads(p.read_text()) for p in args.report])
        if args.views:
            return print(views_report(record))
    elif args.views:
        raise SystemExit("error: --views needs --report JSON [JSON ...]")
    else:
        record = measure(args)
    chart(record, args.chart)
    text = report(record) + f"\n\n![PSNR against wall seconds from launch, both methods](performance/{args.chart.name})"
    print(text)
    if args.write:
        write_between_markers(args.write, text)


def measure(args) -> dict:
    """Every dataset's runs; the JSON is written after every run (an interrupted run keeps them)."""
    if not args.opensplat or not os.access(args.opensplat, os.X_OK):
        print(f"peers: no OpenSplat binary at {args.opensplat!r}: give --opensplat PATH or $OPENSPLAT "
              "(../shared/peers/opensplat/build.sh builds it)", file=sys.stderr)  # fmt: skip
        raise SystemExit(2)
    import torch

    torch.set_num_threads(2)
    if "7scenes" in args.datasets and not (SEVEN_SCENES / "seq").is_dir():
        if args.datasets == ["7scenes"]:
            raise SystemExit(f"error: no dataset to run: 7scenes's shared frames are not at {SEVEN_SCENES} (set $SEGS_SHARED_DATA)")
        print(f"peers: skipping 7scenes: the shared frames are not at {SEVEN_SCENES}", file=sys.stderr)
        args.datasets.remove("7scenes")
    command = " ".join(["python bench/peers.py"] + [a for a in sys.argv[1:] if a != args.opensplat and not a.startswith("--opensplat")])
    record = {"machine": machine(args.opensplat), "command": command, "datasets": []}
    args.work.mkdir(parents=True, exist_ok=True)

    def save() -> None:
        record["machine"]["load_after"] = _load()
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(record, indent=1))

    for name in args.datasets:
        run_dataset(name, args.opensplat, args.budgets or list(DATASETS[name].budgets), args.work, args.seed, record, save, args.tries,
                    args.repeats)
    return record


if __name__ == "__main__":
    main()
