"""`python -m segs.track [+experiment=NAME] [key=value ...]`: tracking only, no Gaussians.

Same configs as `segs.train`: the sequence (`data`) is fed frame by frame to the frontend
(`slam`) through the same frame source (segs.pipeline: here, with the next frames read and their
features built ahead in a reader process, or in a child process for slam_mode=process | live),
then the run folder receives

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
from segs.config import make_sequence, make_source, user_errors_exit, validate
from segs.errors import ConfigError, DataError
from segs.map_points import FILE_NAME as MAP_POINTS
from segs.pipeline.run_state import RunState
from segs.provenance import provenance
from segs.run_folder import write_json_atomic
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
    # slam_mode=interleaved: the next frames are read and their features built in a child process
    # while one is tracked
    source = make_source(cfg, sequence, ahead=PREFETCH, reader="process")
    state = RunState(sequence, source)
    align = OmegaConf.select(cfg, "sensor.ate_align", default=None) or ("sim3" if sequence.sensor == "mono" else "se3")
    if align not in ("se3", "sim3", "none"):
        raise ConfigError(f"sensor.ate_align={align!r} is not one of se3, sim3, none")

    viewer = _viewer(cfg, sequence, state, align)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(sequence), desc="tracking", leave=False, disable=not sys.stderr.isatty())
    t0 = time.perf_counter()
    try:
        with source:
            _track(source, state, bar, viewer)
    except KeyboardInterrupt:
        if bar is not None:
            bar.close()
        _write_partial(out, sequence, state)
        raise
    wall = time.perf_counter() - t0
    if bar is not None:
        bar.close()
    if viewer is not None:
        viewer.tick(len(sequence), force=True)

    traj = state.trajectory()
    write_trajectory(out / "trajectory.txt", sequence.timestamps, traj)  # nothing tracked: empty, ATE n/a
    kfs = state.keyframe_frames()
    with open(out / "keyframes.txt", "w") as f:
        f.write("# kf_id frame_index timestamp\n")
        for k, i in sorted(kfs.items()):
            f.write(f"{k} {i} {sequence.timestamps[i]:.6f}\n")
    state.map_points.write(out / MAP_POINTS)
    lost = state.lost_frames()
    ate_result = frontend_ate(state, sequence.timestamps, traj, sequence.gt_poses, align)
    stats = source.stats()
    n = len(sequence)
    processed = source.frames_done  # live: less than n
    process_s, finish_s = source.process_seconds, source.finish_seconds
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
        "frames_dropped_live": len(state.dropped_frames()),
        "keyframes": len(kfs),
        "ate_rmse_m": ate_result["rmse"],
        "ate": ate_result,
        "step_scale": (step_scale(sequence.timestamps, traj, sequence.gt_poses)
                       if align == "sim3" and sequence.gt_poses is not None
                       and not state.uses_ground_truth_poses else None),
        # process(): tracking and, single-threaded, local mapping and loop closing
        "tracking_fps": processed / process_s if process_s > 0 else None,
        "process_s": process_s,
        "finish_s": finish_s,
        "wall_s": wall,
        # frames per second of the whole run's wall clock (reading, features, tracking, mapping,
        # finish): what the pipelining of reading and features beside tracking buys
        "wall_fps": processed / wall if wall > 0 else None,
        "frontend": stats,
        "points": len(state.map_points),
        "provenance": provenance(cfg, sequence.sensor),
    }
    write_json_atomic(out / "tracking.json", metrics)
    rmse = ate_result["rmse"]
    print(
        f"\nsegs.track: results in {out}\n"
        f"  {len(traj)}/{n} frames tracked ({100 * len(traj) / n:.1f} %), {len(kfs)} keyframes, "
        f"{len(state.map_points)} map points"
        + (f", {stats['depth_retries']} frames by the depth-tolerant retry" if stats.get("depth_retries") else "")
        + "\n"
        f"  ATE RMSE ({align}) {f'n/a ({ate_result.get(REASON)})' if rmse is None else f'{rmse * 100:.2f} cm'}"
        f" over {ate_result['pairs']} frames\n"
        f"  {metrics['tracking_fps'] or 0:.1f} frames/s in process() ({process_s:.1f} s), "
        f"finish {finish_s:.1f} s, wall {wall:.1f} s ({metrics['wall_fps'] or 0:.1f} frames/s)"
        + (f", {metrics['frames_dropped_live']} frames dropped (live)" if metrics["slam_mode"] == "live" else "") + "\n"
        "  trajectory.txt (TUM), keyframes.txt, map_points.ply, tracking.json"
    )
    if viewer is not None:
        from segs.viewer.live import close

        close(viewer.server, out)
    return metrics


def _track(source, run: RunState, bar, viewer) -> None:
    """Every frame of the source through the frame loop, then the frontend's finish; the map
    points of every update logged, the progress bar and the viewer told after each."""
    while not source.exhausted():
        run.map_points.add(source.track(1, timeout=0.2))  # interleaved: one frame; a child: its reports
        if bar is not None:
            bar.update(source.cursor - bar.n)
        if viewer is not None:
            viewer.tick(source.cursor)
    run.map_points.add(run.finish())


def _viewer(cfg: DictConfig, sequence, run: RunState, align: str):
    """The web viewer of viewer=on (segs.viewer.live.TrackingViewer), or None."""
    vcfg = viewer_config(OmegaConf.to_container(cfg.viewer, resolve=True)) if "viewer" in cfg else None
    if vcfg is None:
        return None
    from segs.viewer.live import TrackingViewer

    return TrackingViewer(vcfg, sequence, run, align)


def _write_partial(out: Path, sequence, run: RunState) -> None:
    """Ctrl-C: the poses tracked so far into trajectory_partial.txt (TUM) and the map points so far
    into map_points.ply; no trajectory.txt or tracking.json, so an interrupted run never looks
    finished."""
    try:
        traj, path = run.trajectory(), out / "trajectory_partial.txt"
        n = write_trajectory(path, sequence.timestamps, traj) if traj else 0
        run.map_points.write(out / MAP_POINTS)
        print(f"\nsegs.track: interrupted; {n} of {len(sequence)} frames tracked"
              + (f", their poses in {path}" if n else ""), file=sys.stderr)
    except Exception as exc:  # noqa: BLE001 - the interrupt itself must not be masked
        print(f"\nsegs.track: interrupted; the partial trajectory could not be written ({exc})", file=sys.stderr)


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
