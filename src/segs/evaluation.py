"""End-of-run evaluation (the paper's protocol) and the files a finished run leaves behind.

Test views are all tracked frames whose images were not trained on; each is rendered at its
estimated pose and compared with its image (PSNR, SSIM, LPIPS when weights are configured).
ATE comes from evo. metrics.json is written last and atomically: a run folder without it is not
a finished result. The mapper is used only through segs.modules.contract.GaussianMapper; the run
(trajectory, split, keyframes, map points, tracking speed) through its segs.pipeline RunState.
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import torch
from tqdm import tqdm

from segs.callbacks.memory import peak_rss_mb
from segs.eval_config import EvalConfig
from segs.map_points import FILE_NAME as MAP_POINTS
from segs.modules.contract import GaussianCloud, GaussianMapper
from segs.modules.metrics import make_lpips, psnr, ssim
from segs.pipeline.run_state import RunState
from segs.run_folder import write_json_atomic
from segs.trajectory import GROUND_TRUTH_POSES, estimated_c2w, frontend_ate, lost_ranges, write_tum

log = logging.getLogger(__name__)


def _save_pair(path: Path, render: torch.Tensor, gt: np.ndarray) -> None:
    pair = np.concatenate([render.numpy(), gt], axis=1)
    img = (np.clip(pair, 0, 1) * 255 + 0.5).astype(np.uint8)
    cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))


def render_test_views(module: GaussianMapper, sequence, trajectory: dict, test: list[int], lpips_weights, save_renders: int,
                      out: Path, progress: bool = True, active_threshold: float = 0.005,
                      watch: Callable[[str], None] | None = None) -> dict:  # fmt: skip
    """Render every test frame at its estimated pose; returns the mean metrics and writes renders.

    watch: called with "at test view N" before each view (the memory guard's check)."""
    lpips = make_lpips(lpips_weights)
    lossless = getattr(sequence, "lossless_rgb", None)  # idx -> lossless colour or None
    keep = set(np.asarray(test)[np.linspace(0, len(test) - 1, save_renders).round().astype(int)]) if test and save_renders else set()
    out.mkdir(parents=True, exist_ok=True)
    if keep:
        (out / "renders").mkdir(exist_ok=True)
    rows = []
    for idx in tqdm(test, desc="test views", disable=not progress, leave=False):
        if watch is not None:
            watch(f"at test view {idx}")
        frame = sequence[idx]
        gt = torch.from_numpy(np.ascontiguousarray(frame.rgb))
        render = module.render_image(trajectory[idx], frame.camera)["image"]
        row = {"frame": idx, "psnr": psnr(render, gt), "ssim": ssim(render, gt), "lpips": lpips(render, gt) if lpips else None,
               "active": module.count_active(trajectory[idx], frame.camera, active_threshold)}  # fmt: skip
        clean = lossless(idx) if lossless is not None else None
        if clean is not None:  # the same frame without compression (7-Scenes frames 150-199)
            clean = torch.from_numpy(np.ascontiguousarray(clean))
            row["psnr_lossless"], row["psnr_jpeg_vs_lossless"] = psnr(render, clean), psnr(gt, clean)
        rows.append(row)
        if idx in keep:
            _save_pair(out / "renders" / f"test_{idx:05d}.png", render, frame.rgb)
    with open(out / "test_views.csv", "w") as f:
        f.write("frame,psnr,ssim,lpips\n")
        for r in rows:
            lp = "" if r["lpips"] is None else f"{r['lpips']:.5f}"
            f.write(f"{r['frame']},{r['psnr']:.4f},{r['ssim']:.5f},{lp}\n")
    mean = lambda k: float(np.mean([r[k] for r in rows])) if rows and rows[0][k] is not None else None  # noqa: E731
    out = {"psnr": mean("psnr"), "ssim": mean("ssim"), "lpips": mean("lpips"), "test_views": len(rows),
           "active_gaussians": mean("active"), "renders_saved": len(keep)}  # fmt: skip
    clean = [r for r in rows if "psnr_lossless" in r]
    if clean:  # PSNR against lossless frames, beside the same views' PSNR against the JPEGs
        out.update({"lossless_views": len(clean), "psnr_lossless": float(np.mean([r["psnr_lossless"] for r in clean])),
                    "psnr_jpeg_on_lossless_views": float(np.mean([r["psnr"] for r in clean])),
                    "psnr_jpeg_vs_lossless": float(np.mean([r["psnr_jpeg_vs_lossless"] for r in clean]))})
    return out


def write_ply(module: GaussianMapper, path: Path, fit_steps: int, sequence, trajectory: dict, test: list[int],
              progress: bool = True) -> dict:  # fmt: skip
    """Write point_cloud.ply: for a map decoded per view (SEGS) its Gaussians fitted for fit_steps
    steps to the training views (GaussianMapper.fitted_cloud), scored on the test views as a
    standard 3D-GS renderer draws them; otherwise the model's own export, not scored.
    Returns {"ply_gaussians": written, "ply_psnr": mean test-view PSNR or None}."""
    with tqdm(total=fit_steps, desc="fitting the PLY", disable=not progress or fit_steps == 0, leave=False) as bar:
        cloud = module.fitted_cloud(fit_steps, progress=lambda step: bar.update(1))
    written = module.export_ply(path, cloud)
    score = cloud_psnr(module, cloud, sequence, trajectory, test) if cloud is not None and test else None
    return {"ply_gaussians": written, "ply_psnr": score}


@torch.no_grad()
def cloud_psnr(module: GaussianMapper, cloud: GaussianCloud, sequence, trajectory: dict, test: list[int]) -> float:
    """Mean PSNR of the test frames `test` drawn from `cloud` at their estimated poses as a
    standard 3D-GS renderer draws them (GaussianMapper.render_cloud)."""
    gaussians = (cloud.means, cloud.quats, cloud.scales, cloud.opacities, cloud.colors)
    scores = []
    for idx in test:
        frame = sequence[idx]
        render = module.render_cloud(gaussians, trajectory[idx], frame.camera).clamp(0, 1).cpu()
        scores.append(psnr(render, torch.from_numpy(np.ascontiguousarray(frame.rgb))))
    return float(np.mean(scores))


def run_summary(module: GaussianMapper, sequence, run: RunState, timing: dict) -> dict:
    """The numbers of a run that need no rendering: time, tracking, keyframes, model size.

    timing: {"steps", "fit_s", "wall_s"} summed over every session of the run (resumes included),
    and "scheduled_steps" (model.total_steps: the schedules' length; more than "steps" when
    trainer.max_time stopped the run first, or a coarse-to-fine run is shorter than
    mapping.min_schedule_steps).
    """
    trajectory = run.trajectory()
    lost = run.lost_frames()
    counts = module.counts()
    steps = timing.get("steps", 0)
    dropped = int(getattr(sequence, "dropped", 0) or 0)
    summary = {
        "sequence": getattr(sequence, "name", ""),
        "iterations": steps,
        "scheduled_iterations": timing.get("scheduled_steps"),
        "wall_time_s": timing.get("wall_s"),
        "mapping_time_s": timing.get("fit_s"),
        "iterations_per_s": steps / timing["fit_s"] if timing.get("fit_s") else None,
        "iteration_ms_median": float(np.median(module.iteration_ms)) if module.iteration_ms else None,
        "sessions": timing.get("sessions", 1),
        "tracking_fps": run.tracking_fps(),
        "frames": len(sequence),
        "frames_dropped": dropped,
        "frames_tracked": len(trajectory),
        "tracked_fraction": len(trajectory) / max(len(sequence), 1),
        "lost_frames": len(lost),
        "lost_ranges": lost_ranges(lost),
        # slam_mode=live: frames skipped because tracking was behind the camera (never tracked)
        "frames_dropped_live": len(run.dropped_frames()),
        "keyframes": len(run.keyframe_frames()),
        "training_views": counts.training_views,
        "held_out_points": run.held_out_points,
        "anchors": counts.anchors,
        "gaussians": counts.gaussians,
        "params": counts.params,
        "model_mb": counts.mb,
        "peak_rss_mb": peak_rss_mb(),
    }
    if dropped:
        summary["frames_note"] = (f"{dropped} frames listed by the dataset were left out when it was read (no depth / right "
                                  "image within the association tolerance); frames counts the ones used")  # fmt: skip
    return summary


def mapper_provenance(module: GaussianMapper, provenance: dict | None) -> dict:
    """The run's provenance with what the mapper did: the rasterizer backend that rendered and
    whether the step's tensor code ran compiled."""
    return {**(provenance or {}), "raster_backend": module.raster_backend, "compiled_step_code": module.compiled}


def evaluate(module: GaussianMapper, sequence, run: RunState, eval_cfg: EvalConfig, out: Path, timing: dict, notes: dict | None = None,
             watch: Callable[[str], None] | None = None, provenance: dict | None = None) -> dict:  # fmt: skip
    """Compute and write every result file of a run; returns the metrics dict (metrics.json, last).

    notes: extra entries for metrics.json (e.g. why the final checkpoint is missing);
    watch: called before each test view (memory guard); provenance: segs.provenance's record,
    completed here with the raster backend that rendered the test views."""
    out.mkdir(parents=True, exist_ok=True)
    trajectory = run.trajectory()
    test = run.test_frames()
    images = render_test_views(module, sequence, trajectory, test, eval_cfg.lpips_weights, eval_cfg.save_renders, out,
                               eval_cfg.progress, eval_cfg.active_opacity, watch)  # fmt: skip
    idx, c2w = estimated_c2w(trajectory)
    write_tum(out / "trajectory.txt", sequence.timestamps[idx], c2w)
    ate_result = frontend_ate(run, sequence.timestamps, trajectory, sequence.gt_poses, eval_cfg.ate_align)
    ply = {"ply_gaussians": None, "ply_psnr": None}
    if eval_cfg.write_ply:
        ply = write_ply(module, out / "point_cloud.ply", eval_cfg.ply_fit_steps, sequence, trajectory, test, eval_cfg.progress)
    run.map_points.write(out / MAP_POINTS)
    summary = run_summary(module, sequence, run, timing)
    metrics = {
        **images,
        "lpips_note": None if images["lpips"] is not None else "n/a: no AlexNet weights file (eval.lpips_weights)",
        "ate_rmse_m": ate_result["rmse"],
        "ate": ate_result,
        **ply,
        **summary,
        **(notes or {}),
        "status": "finished",
        "provenance": mapper_provenance(module, provenance),
    }
    if not test:
        metrics["test_note"] = ("no test view: every tracked frame was trained on (each became a keyframe); "
                                "eval.holdout_every=N keeps every N-th frame out of training to test on")
    if ate_result.get("reason") == GROUND_TRUTH_POSES:
        metrics["ate_note"] = "n/a: the frontend replays the ground-truth poses (slam=known_poses); no trajectory was estimated"
    elif summary["lost_frames"]:
        metrics["ate_note"] = f"{summary['lost_frames']} untracked frames have no pose and are excluded from ATE and test views"
    write_json_atomic(out / "metrics.json", metrics)
    return metrics


def write_not_evaluated(module: GaussianMapper, sequence, run: RunState, out: Path, timing: dict, notes: dict | None = None,
                        provenance: dict | None = None) -> dict:  # fmt: skip
    """metrics.json of a run trained with eval.enabled=false (status "not_evaluated"): the run's
    numbers without any test-view or trajectory metric."""
    out.mkdir(parents=True, exist_ok=True)
    run.map_points.write(out / MAP_POINTS)
    none = dict.fromkeys(("psnr", "ssim", "lpips", "ate_rmse_m", "active_gaussians"))
    metrics = {**none, "test_views": 0, **run_summary(module, sequence, run, timing), **(notes or {}), "status": "not_evaluated",
               "eval_note": "eval.enabled=false: no test view was rendered and no ATE computed",
               "provenance": mapper_provenance(module, provenance)}  # fmt: skip
    write_json_atomic(out / "metrics.json", metrics)
    return metrics


def write_tracking_failed(out: Path, err, frames_tracked: int, wall_s: float, provenance: dict | None = None) -> dict:
    """metrics.json of a run whose frontend tracked nothing mappable (status "tracking_failed"):
    the tracking numbers it has, no image or model metric. err: the TrackingFailed raised;
    provenance: segs.provenance's record."""
    out.mkdir(parents=True, exist_ok=True)
    none = dict.fromkeys(("psnr", "ssim", "lpips", "ate_rmse_m", "mapping_time_s", "iterations_per_s", "tracking_fps"))
    metrics = {
        **none,
        "status": "tracking_failed",
        "reason": str(err),
        "test_views": 0,
        "iterations": 0,
        "wall_time_s": wall_s,
        "frames": err.frames,
        "frames_tracked": frames_tracked,
        "tracked_fraction": frames_tracked / max(err.frames, 1),
        "lost_frames": err.lost,
        "training_views": 0,
        "anchors": 0,
        "gaussians": 0,
        "peak_rss_mb": peak_rss_mb(),
        "provenance": provenance,
    }
    write_json_atomic(out / "metrics.json", metrics)
    return metrics
