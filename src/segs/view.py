"""`python -m segs.view RUN_DIR [--host H] [--port P]`: a run folder in the web viewer.

Any run folder of segs.train or segs.track, finished or interrupted: the Gaussians
(point_cloud.ply, as the run exported them; without it or when a checkpoint is newer, an
interrupted run, decoded by the mapper rebuilt from checkpoints/final.ckpt, else last.ckpt, for
each browser's camera: what a render from there draws, decoded again when that camera has moved
and settled; a run with both: the PLY, or the checkpoint's decoding, chosen in each browser's panel), the
SLAM map points (map_points.ply), the estimated trajectory
(trajectory.txt or trajectory_partial.txt) beside the ground truth when the run's data can still be read, the keyframes (selecting one shows
its image and the render from its pose) and the run's numbers. Serves until Ctrl-C. Defaults of
--host / --port / --first-port: conf/viewer/on.yaml. A busy --port, a folder that is not a run:
one line, exit 2.
"""
from __future__ import annotations

if __name__ == "__main__":  # the program: process settings before torch loads (docs/decisions/028-process-settings.md)
    from segs import process_settings

    process_settings.apply()

import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from segs.config import CONF_DIR, make_sequence, user_errors_exit
from segs.errors import UserInputError
from segs.viewer.saved_run import SavedRun, read_gaussian_ply, read_run
from segs.viewer.scene import (
    EVERY_ONE,
    BrowserCamera,
    DecodedCameras,
    KeyframeNode,
    Snapshot,
    Trajectories,
    splats_for,
    splats_for_each,
    thumbnail,
)

log = logging.getLogger("segs.view")


def load_mapper(run: SavedRun):
    """The mapper of the run's checkpoint (on the CPU, the run's own config), or None."""
    if run.kind != "train" or run.checkpoint is None:
        return None
    import torch

    from segs.modules.config import build_model, mapping_config, raster_config
    from segs.modules.gaussian_mapper import GaussianMapperModule

    cfg = run.config
    raster = {**OmegaConf.to_container(cfg.raster, resolve=True), "backend": "auto"}  # a GPU run viewed on a CPU
    module = GaussianMapperModule(build_model(cfg.model), mapping_config(cfg.mapping), raster_config(raster), seed=int(cfg.seed))
    try:
        ckpt = torch.load(run.checkpoint, map_location="cpu", weights_only=False)
        module.on_load_checkpoint(ckpt)
        module.load_state_dict(ckpt["state_dict"])
    except Exception as err:  # noqa: BLE001 - any reader error means the same to the user
        raise UserInputError(f"{run.checkpoint}: not a readable checkpoint of this run ({type(err).__name__})") from None
    return module.eval()


def load_sequence(run: SavedRun):
    """(the run's sequence, None) or (None, why it cannot be read): ground truth and images."""
    try:
        return make_sequence(run.config.data), None
    except (UserInputError, OSError, KeyError, ValueError) as err:
        return None, f"the run's data cannot be read ({' '.join(str(err).split())[:100]})"


def shows_ply(run: SavedRun) -> bool:
    """Whether the viewer shows the run's point_cloud.ply (not older than its checkpoint)."""
    return run.ply is not None and (run.checkpoint is None or run.ply.stat().st_mtime >= run.checkpoint.stat().st_mtime)


def snapshot(run: SavedRun, mapper, sequence, note: str | None, cameras: dict[int, BrowserCamera] | None = None, splats_id: int = 1,
             shared: bool = True, dropped: set[int] | frozenset[int] = frozenset()) -> Snapshot:
    """Everything the run folder shows, as one snapshot, numbered splats_id. With shared, the
    Gaussians every browser without its own sees: those of its point_cloud.ply when shows_ply,
    else the checkpoint's, every one decoded for the first keyframe; the checkpoint's decoded
    for each of `cameras` (client id -> camera), each browser's own; `dropped`: browsers shown the
    shared Gaussians again."""
    splats, ply = None, shows_ply(run)
    if shared and ply:
        splats = read_gaussian_ply(run.ply).visible()  # what the run exported (SEGS: fitted, eval.ply_fit_steps)
    elif shared and mapper is not None:
        splats = splats_for(mapper, None)
    per_browser = splats_for_each(mapper, cameras) if mapper is not None and cameras else {}
    align = OmegaConf.select(run.config, "sensor.ate_align", default="se3") or "se3"
    trajs = None
    if run.trajectory is not None:
        gt = (np.asarray(sequence.timestamps), sequence.gt_poses) if sequence is not None else (None, None)
        trajs = Trajectories(run.trajectory[0], run.trajectory[1], gt[0], gt[1], align)
    points = run.points or (None, None)
    return Snapshot(splats=splats, splats_id=splats_id, splats_label="point_cloud.ply" if ply else EVERY_ONE, per_browser=per_browser,
                    dropped=frozenset(dropped), points=points[0], point_colors=points[1], trajectories=trajs,
                    keyframes=keyframes(run, mapper, sequence), panel=panel(run, mapper, note))  # fmt: skip


def keyframes(run: SavedRun, mapper, sequence) -> list[KeyframeNode]:
    """The training views of the mapper, or the keyframes of keyframes.txt at their poses of
    the trajectory (their images from the run's data, when it can be read)."""
    if mapper is not None:
        return [KeyframeNode(v.kf_id, v.frame_index, v.w2c.numpy().astype(np.float64), v.camera, thumbnail(v.image.numpy()))
                for v in mapper.training_views()]  # fmt: skip
    if sequence is None or run.trajectory is None or not run.keyframes:
        return []
    out = []
    for kf_id, index in run.keyframes:
        if (w2c := run.w2c_at(sequence.timestamps[index])) is not None:
            image = (np.clip(sequence[index].rgb, 0, 1) * 255 + 0.5).astype(np.uint8)
            out.append(KeyframeNode(kf_id, index, w2c, sequence.camera, thumbnail(image)))
    return out


def panel(run: SavedRun, mapper, note: str | None) -> dict[str, str]:
    r = run.results
    fmt = lambda key, spec, unit="": "n/a" if r.get(key) is None else f"{r[key]:{spec}}{unit}"  # noqa: E731
    rows = {"run": f"{run.kind} ({run.status.replace('_', ' ')}): {run.path.name}"}
    if run.kind == "train":
        counts = mapper.counts() if mapper is not None else None
        rows["step"] = str(r.get("iterations", mapper.restored_step if mapper is not None else "n/a"))
        rows["test PSNR so far"] = f"{fmt('psnr', '.2f', ' dB')} ({r.get('test_views', 0)} test views)" if r else "n/a (not evaluated)"
        rows["anchors"] = str(counts.anchors if counts else r.get("anchors", "n/a"))
        rows["Gaussians"] = str(counts.gaussians if counts else r.get("gaussians", "n/a"))
        rows["training"] = fmt("iterations_per_s", ".1f", " steps/s")
    else:
        rows["Gaussians"] = "0 (tracking only)"
        rows["keyframes"] = str(len(run.keyframes))
        rows["ATE RMSE"] = "n/a" if r.get("ate_rmse_m") is None else f"{r['ate_rmse_m'] * 100:.2f} cm"
    rows["map points"] = str(len(run.points[0]) if run.points is not None else "n/a (no map_points.ply)")
    rows["frames tracked"] = f"{r['frames_tracked']} of {r['frames']}" if "frames_tracked" in r else "n/a"
    rows["tracking"] = fmt("tracking_fps", ".1f", " frames/s")
    rows["frames dropped (live)"] = str(r.get("frames_dropped_live", "n/a"))
    if note:
        rows["note"] = note
    return rows


def provider(run: SavedRun, mapper, sequence):
    """kf_id -> (image, render or None, note) for a keyframe selected in the browser."""
    from segs.modules.contract import to_uint8

    def show(kf_id: int):
        if mapper is not None:
            view = next((v for v in mapper.training_views() if v.kf_id == kf_id), None)
            if view is not None:
                render = to_uint8(mapper.render_image(view.w2c, view.camera, view.kf_id)["image"]).numpy()
                return view.image.numpy(), render, f"keyframe {kf_id} (frame {view.frame_index}): image | render"
        index = dict(run.keyframes).get(kf_id)
        if index is None or sequence is None:
            return np.zeros((8, 8, 3), np.uint8), None, f"keyframe {kf_id}: no image (the run's data cannot be read)"
        why = "tracking only: no map to render" if run.kind == "track" else "no checkpoint: no render"
        return (np.clip(sequence[index].rgb, 0, 1) * 255 + 0.5).astype(np.uint8), None, f"keyframe {kf_id} (frame {index}): image ({why})"

    return show


PLY, CAMERA = "point_cloud.ply (as a 3D-GS viewer shows it)", "decoded for this camera (the map's render)"


class CameraFollower:
    """What segs.view draws of the map for each browser, kept up to date: the checkpoint's
    Gaussians decoded again for its camera once it has moved and settled, or the run's
    point_cloud.ply (the same from everywhere, the shared Gaussians). choices: whether each browser
    chooses between the two (its PLY / CAMERA dropdown, server.browser_choices) when the run has
    both; without, a run with a current PLY shows it, one without, its checkpoint decoded for
    every browser's camera."""

    def __init__(self, server, run: SavedRun, mapper, sequence, note: str | None, choices: bool = False):
        self.server, self.args, self.choices = server, (run, mapper, sequence, note), choices
        self.fixed = PLY if shows_ply(run) or mapper is None else CAMERA
        self.own: set[int] = set()  # browsers drawing the checkpoint decoded for their camera now
        self.seen: dict[int, str] = {}  # each browser's source at the latest call
        self.decoded = DecodedCameras()
        self.snapshots = 1  # submitted so far (serve's first one included)

    def sources(self) -> dict[int, str]:
        """What each connected browser (client id) draws: PLY or CAMERA."""
        if self.choices:
            return self.server.browser_choices()
        return dict.fromkeys(self.server.browser_cameras(), self.fixed)

    def __call__(self) -> bool:
        """Submit a new snapshot when browsers switched (a decoding for the cameras of those that
        chose CAMERA, the shared Gaussians again for those that chose PLY) or, decoding for them,
        when cameras of browsers at CAMERA moved and settled (theirs alone); returns whether one was."""
        if self.fixed == PLY and not self.choices:
            return False
        sources = self.sources()
        switched = {cid for cid, src in sources.items() if src == CAMERA != self.seen.get(cid, CAMERA)}
        self.seen, self.own = sources, self.own & sources.keys()  # gone: the server drops theirs
        dropped = {cid for cid in self.own if sources[cid] != CAMERA}
        cameras = {cid: cam for cid, cam in self.server.browser_cameras().items() if sources.get(cid) == CAMERA}
        todo = {**self.decoded.moved(cameras), **{cid: cam for cid, cam in cameras.items() if cid in switched}}
        if not todo and not dropped:
            return False
        self.decoded.mark(todo)
        self.own = (self.own - dropped) | todo.keys()
        self.snapshots += 1
        self.server.submit(snapshot(*self.args, cameras=todo, splats_id=self.snapshots, shared=False, dropped=dropped))
        return True


def serve(run_dir: str | Path, host: str, port: int | None, first_port: int):
    """Start serving the run: (server, selection provider, camera follower); the caller answers
    selections and calls the follower. The folder and the port are checked first, before the
    checkpoint and the data are read."""
    from segs.viewer.config import viewer_config
    from segs.viewer.live import start_server

    run = read_run(run_dir)
    cfg = OmegaConf.merge(OmegaConf.load(CONF_DIR / "viewer" / "on.yaml"), {"host": host, "port": port, "first_port": first_port})
    server = start_server(viewer_config(OmegaConf.to_container(cfg)), f"segs.view: {run.path.name}")
    try:
        mapper = load_mapper(run)
        sequence, note = load_sequence(run)
        server.submit(snapshot(run, mapper, sequence, note))
        choices = mapper is not None and shows_ply(run)
        if choices:
            server.add_choice("Gaussians", (PLY, CAMERA), PLY, "the exported PLY, or the map decoded for this camera")
    except BaseException:
        server.close()
        raise
    return server, provider(run, mapper, sequence), CameraFollower(server, run, mapper, sequence, note, choices)


def main(argv: list[str] | None = None) -> None:
    defaults = OmegaConf.load(CONF_DIR / "viewer" / "on.yaml")
    parser = argparse.ArgumentParser(prog="python -m segs.view", description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", help="a run folder of segs.train or segs.track")
    parser.add_argument("--host", default=defaults.host, help=f"address to serve on (default {defaults.host})")
    parser.add_argument("--port", type=int, default=defaults.port,
                        help="serve on this port, or exit 2 when it is busy (default: the first free one)")
    parser.add_argument("--first-port", type=int, default=defaults.first_port,
                        help=f"the first port tried without --port (default {defaults.first_port})")
    args = parser.parse_args(argv)
    with user_errors_exit():
        server, answer, follow = serve(args.run_dir, args.host, args.port, args.first_port)
    try:
        while True:
            server.serve_selection(answer)
            follow()
            time.sleep(0.05)
    except KeyboardInterrupt:
        server.close()
        print("\nsegs.view: stopped", file=sys.stderr)


if __name__ == "__main__":
    main()
