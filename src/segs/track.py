"""`python -m segs.track [+experiment=NAME] [key=value ...]`: tracking only, no Gaussians.

Same configs as `segs.train`: the sequence (`data`) is fed frame by frame to the frontend
(`slam`), then the run folder receives

- trajectory.txt: the estimated camera-to-world poses of the tracked frames (TUM format),
- keyframes.txt: `kf_id frame_index timestamp` of the keyframes still in the map,
- map_points.ply: the SLAM map points (x y z, colour, creating kf_id; segs.map_points),
- tracking.json: ATE RMSE (evo; SE(3) for RGB-D / stereo, Sim(3) for monocular, from
  `sensor.ate_align`), tracking FPS, tracked fraction, lost frame ranges and frontend statistics;
  with a Sim(3) alignment also the step scale (`segs.trajectory.step_scale`: estimated / true
  path length over every 5 consecutive steps, its median and min / max relative to the median).

Run folder: outputs/track/runs/<time> (task_name=track unless given).
"""
from __future__ import annotations

import logging
import sys
import time
from pathlib import Path

import hydra
from omegaconf import DictConfig, OmegaConf

from segs import process_settings
from segs.config import make_frontend, make_sequence, user_errors_exit, validate
from segs.errors import ConfigError, DataError
from segs.map_points import FILE_NAME as MAP_POINTS
from segs.map_points import MapPointLog
from segs.provenance import provenance
from segs.run_folder import write_json_atomic
from segs.slam.runtime.process import FrontendProcess
from segs.slam.runtime.runner import RunResult, run_sequence
from segs.trajectory import frontend_ate, lost_ranges, step_scale, write_trajectory
from segs.viewer.config import viewer_config

log = logging.getLogger("segs.track")
# frames read and prepared ahead of tracking, in a child process (slam_mode=interleaved): enough to
# cover a keyframe's local mapping (docs/decisions/014-frame-reader-process.md)
PREFETCH = 16
REASON = "reason"  # why tracking.json's ate has no figure


def run(cfg: DictConfig, progress: bool = True) -> dict:
    """Track the configured sequence; writes the result files and returns tracking.json's dict."""
    validate(cfg, mapper=False)
    out = Path(cfg.paths.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    sequence = make_sequence(cfg.data)
    if len(sequence) == 0:
        raise DataError(f"data: the sequence at {cfg.data.get('root', '?')} has no frames")
    frontend = make_frontend(cfg, sequence)
    align = OmegaConf.select(cfg, "sensor.ate_align", default=None) or ("sim3" if sequence.sensor == "mono" else "se3")
    if align not in ("se3", "sim3", "none"):
        raise ConfigError(f"sensor.ate_align={align!r} is not one of se3, sim3, none")

    points = MapPointLog()  # every map point handed over, moved by loop corrections (map_points.ply)
    viewer = _viewer(cfg, sequence, frontend, points, align)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(sequence), desc="tracking", leave=False, disable=not sys.stderr.isatty())
    t0 = time.perf_counter()
    try:
        if isinstance(frontend, FrontendProcess):
            try:
                result = _run_process(frontend, bar, points, viewer)
            finally:
                frontend.close()
        else:
            def on_frame(frame, res) -> None:
                if bar is not None:
                    bar.update(1)
                if viewer is not None:
                    viewer.tick(frame.index + 1)

            # the next frames are read and their features built in a child process while one is tracked
            result = run_sequence(frontend, sequence, on_frame=on_frame, prefetch=PREFETCH, reader="process", on_update=points.add)
    except KeyboardInterrupt:
        if bar is not None:
            bar.close()
        _write_partial(out, sequence, frontend, points)
        raise
    wall = time.perf_counter() - t0
    if bar is not None:
        bar.close()
    if viewer is not None:
        viewer.tick(len(sequence), force=True)

    traj = frontend.trajectory()
    write_trajectory(out / "trajectory.txt", sequence.timestamps, traj)  # nothing tracked: empty, ATE n/a
    kfs = frontend.keyframe_frames()
    with open(out / "keyframes.txt", "w") as f:
        f.write("# kf_id frame_index timestamp\n")
        for k, i in sorted(kfs.items()):
            f.write(f"{k} {i} {sequence.timestamps[i]:.6f}\n")
    points.write(out / MAP_POINTS)
    lost = frontend.lost_frames()
    ate_result = frontend_ate(frontend, sequence.timestamps, traj, sequence.gt_poses, align)
    stats = frontend.stats() if hasattr(frontend, "stats") else {}
    n = len(sequence)
    processed = frontend.frames_done if isinstance(frontend, FrontendProcess) else n  # live: less
    metrics = {
        "sequence": getattr(sequence, "name", ""),
        "sensor": sequence.sensor,
        "frames": n,
        "frames_dropped": int(getattr(sequence, "dropped", 0) or 0),  # listed by the dataset, left out when read
        "frames_tracked": len(traj),
        "tracked_fraction": len(traj) / n,
        "lost_frames": len(lost),
        "lost_ranges": lost_ranges(lost),
        "slam_mode": OmegaConf.select(cfg, "slam_mode", default="interleaved"),
        # slam_mode=live: frames skipped because tracking was behind the camera (never tracked)
        "frames_dropped_live": len(frontend.dropped_frames()) if isinstance(frontend, FrontendProcess) else 0,
        "keyframes": len(kfs),
        "ate_rmse_m": ate_result["rmse"],
        "ate": ate_result,
        "step_scale": (step_scale(sequence.timestamps, traj, sequence.gt_poses)
                       if align == "sim3" and sequence.gt_poses is not None
                       and not getattr(frontend, "uses_ground_truth_poses", False) else None),
        # process(): tracking and, single-threaded, local mapping and loop closing
        "tracking_fps": processed / result.process_s if result.process_s > 0 else None,
        "process_s": result.process_s,
        "finish_s": result.finish_s,
        "wall_s": wall,
        # frames per second of the whole run's wall clock (reading, features, tracking, mapping,
        # finish): what the pipelining of reading and features beside tracking buys
        "wall_fps": processed / wall if wall > 0 else None,
        "frontend": stats,
        "points": int(len(result.update.points)),
        "provenance": provenance(cfg, sequence.sensor),
    }
    write_json_atomic(out / "tracking.json", metrics)
    rmse = ate_result["rmse"]
    print(
        f"\nsegs.track: results in {out}\n"
        f"  {len(traj)}/{n} frames tracked ({100 * len(traj) / n:.1f} %), {len(kfs)} keyframes, "
        f"{len(result.update.points)} map points"
        + (f", {stats['depth_retries']} frames by the depth-tolerant retry" if stats.get("depth_retries") else "")
        + "\n"
        f"  ATE RMSE ({align}) {f'n/a ({ate_result.get(REASON)})' if rmse is None else f'{rmse * 100:.2f} cm'}"
        f" over {ate_result['pairs']} frames\n"
        f"  {metrics['tracking_fps'] or 0:.1f} frames/s in process() ({result.process_s:.1f} s), "
        f"finish {result.finish_s:.1f} s, wall {wall:.1f} s ({metrics['wall_fps'] or 0:.1f} frames/s)"
        + (f", {metrics['frames_dropped_live']} frames dropped (live)" if metrics["slam_mode"] == "live" else "") + "\n"
        "  trajectory.txt (TUM), keyframes.txt, map_points.ply, tracking.json"
    )
    if viewer is not None:
        from segs.viewer.live import close

        close(viewer.server, out)
    return metrics


def _viewer(cfg: DictConfig, sequence, frontend, points: MapPointLog, align: str):
    """The web viewer of viewer=on (segs.viewer.live.TrackingViewer), or None."""
    vcfg = viewer_config(OmegaConf.to_container(cfg.viewer, resolve=True)) if "viewer" in cfg else None
    if vcfg is None:
        return None
    from segs.viewer.live import TrackingViewer

    return TrackingViewer(vcfg, sequence, frontend, points, align)


def _write_partial(out: Path, sequence, frontend, points: MapPointLog) -> None:
    """Ctrl-C: the poses tracked so far into trajectory_partial.txt (TUM) and the map points so far
    into map_points.ply; no trajectory.txt or tracking.json, so an interrupted run never looks
    finished."""
    try:
        traj, path = frontend.trajectory(), out / "trajectory_partial.txt"
        n = write_trajectory(path, sequence.timestamps, traj) if traj else 0
        points.write(out / MAP_POINTS)
        print(f"\nsegs.track: interrupted; {n} of {len(sequence)} frames tracked"
              + (f", their poses in {path}" if n else ""), file=sys.stderr)
    except Exception as exc:  # noqa: BLE001 - the interrupt itself must not be masked
        print(f"\nsegs.track: interrupted; the partial trajectory could not be written ({exc})", file=sys.stderr)


def _run_process(frontend: FrontendProcess, bar, points: MapPointLog, viewer) -> RunResult:
    """Wait for a frontend process to track the sequence; process_s is the child's own time
    in process() (its throughput), finish_s is not separated from it (0)."""
    result = RunResult()
    while not frontend.done():
        update = frontend.poll(timeout=0.2)
        points.add(update)
        result.update = result.update.merge(update)
        if bar is not None:
            bar.update(frontend.cursor - bar.n)
        if viewer is not None:
            viewer.tick(frontend.cursor)
    result.process_s = frontend.process_seconds
    return result


@hydra.main(config_path="../../conf", config_name="train", version_base="1.3")
def main(cfg: DictConfig) -> float | None:
    with user_errors_exit():
        try:
            metrics = run(cfg)
        except KeyboardInterrupt:
            sys.exit(130)
    return metrics.get("ate_rmse_m")


if __name__ == "__main__":
    process_settings.apply()  # nothing above loads torch (docs/decisions/028-process-settings.md)
    if not any(a.startswith(("task_name=", "+task_name=", "++task_name=")) for a in sys.argv[1:]):
        sys.argv.append("task_name=track")
    main()
