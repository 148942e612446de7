"""The viewer during a run: `LiveViewer` (a Lightning callback of segs.train) and
`TrackingViewer` (called by segs.track after each frame).

Both take a snapshot at most every `viewer.refresh_s` seconds (training: and with at most
`viewer.max_share` of the training thread's time) and only while a browser is connected; training
takes one sooner when a browser's camera has moved and settled (within the same share). On the
training thread, between two steps, the Gaussians are decoded for each browser's camera
(GaussianMapper.gaussians: what a render from there draws; a SEGS map decodes its Gaussians per
view; a snapshot for moved cameras decodes for those alone), one held-out frame is rendered for
the panel's PSNR, and the copies are handed to the server's drawing thread, which does everything else (covariances, the ground-truth
alignment, encoding, sending). A keyframe selected in a browser is rendered between two steps.
"""
from __future__ import annotations

import logging
import time
from collections import deque

import lightning as L
import numpy as np
import torch

from segs.callbacks.bridge import SlamBridge
from segs.data.frame import Sequence
from segs.map_points import MapPointLog
from segs.modules.contract import GaussianMapper, to_uint8
from segs.modules.metrics import psnr
from segs.trajectory import estimated_c2w
from segs.viewer.config import ViewerConfig
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
from segs.viewer.server import ViewerServer

log = logging.getLogger(__name__)


def start_server(cfg: ViewerConfig, title: str) -> ViewerServer:
    """The server, its address printed (and a skipped busy port said) in one line each."""
    server = ViewerServer(cfg.host, cfg.port, cfg.first_port, title)
    if server.note:
        print(server.note, flush=True)
    print(f"viewer: {server.url}  (open it in a browser; over SSH: ssh -L {server.port}:localhost:{server.port} HOST)", flush=True)
    return server


def close(server: ViewerServer, run_dir) -> None:
    """Stop serving once the last snapshot is drawn; say how to see the run again."""
    server.wait_idle(timeout=30)
    server.close()
    print(f"viewer: closed; python -m segs.view {run_dir} shows the run", flush=True)


def trajectories(sequence: Sequence, trajectory: dict[int, np.ndarray], align: str) -> Trajectories:
    """The frontend's trajectory (frame index -> w2c) and the sequence's ground truth."""
    idx, c2w = estimated_c2w(trajectory)
    return Trajectories(np.asarray(sequence.timestamps)[idx], c2w, np.asarray(sequence.timestamps), sequence.gt_poses, align)


def _fps(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.1f} frames/s"


def dropped(run) -> str:
    """Frames dropped by slam_mode=live (only a frontend in its own process drops frames)."""
    return "0 (frames are not dropped in this mode)" if run.mode == "interleaved" else str(len(run.dropped_frames()))


class LiveViewer(L.Callback):
    """Serves the map while segs.train runs (see the module docstring). align: the run's ATE
    alignment (se3 / sim3 / none), used to draw the ground truth in the estimated frame."""

    def __init__(self, cfg: ViewerConfig, sequence: Sequence, align: str = "se3"):
        self.cfg, self.sequence, self.align = cfg, sequence, align
        self.server = start_server(cfg, f"segs.train: {getattr(sequence, 'name', '')}")
        self.bridge: SlamBridge | None = None
        self.snapshot_ms: list[float] = []  # time each snapshot took on the training thread
        self.camera_ms: list[float] = []  # the same, of the snapshots taken early for a moved camera
        self._last = -float("inf")
        self._last_step = 0
        self._test: deque[tuple[int, float, int]] = deque(maxlen=max(cfg.test_views, 1))  # (frame, psnr, step)
        self._turn = 0
        self._splats_id = 0
        self._thumbs: dict[int, np.ndarray] = {}
        self._decoded = DecodedCameras()
        self._shared_sent = False  # whether the shared Gaussians (for browsers without a camera) were decoded once

    def on_train_start(self, trainer, pl_module) -> None:
        self.bridge = next((c for c in trainer.callbacks if isinstance(c, SlamBridge)), None)
        self._last_step, self._t_step = trainer.global_step, time.perf_counter()

    def period(self) -> float:
        """Seconds between two snapshots: refresh_s, or longer when the last snapshot took more
        than max_share of it on the training thread."""
        return max(self.cfg.refresh_s, self.min_period())

    def min_period(self) -> float:
        """The shortest gap that keeps snapshots within max_share of the training thread."""
        return (self.snapshot_ms[-1] / 1000.0 if self.snapshot_ms else 0.0) / self.cfg.max_share

    def on_train_batch_end(self, trainer, pl_module: GaussianMapper, outputs, batch, batch_idx) -> None:
        self.server.serve_selection(lambda kf_id: self._selection(pl_module, kf_id))
        now = time.perf_counter()
        if not self.server.clients():
            return
        since = now - self._last
        due = since >= self.period()
        moved = {} if due or since < self.min_period() else self._decoded.moved(self.server.browser_cameras())
        if not due and not moved:
            return
        self._last = now
        self.refresh(trainer, pl_module, test_view=due, cameras=None if due else moved)  # moved cameras: no test frame
        self.snapshot_ms.append((time.perf_counter() - now) * 1000.0)
        if not due:
            self.camera_ms.append(self.snapshot_ms[-1])

    def on_train_end(self, trainer, pl_module: GaussianMapper) -> None:
        if self.server.clients():
            self.refresh(trainer, pl_module)
        if self.snapshot_ms:
            self.server.wait_idle(timeout=30)
            log.info("viewer: %d snapshots, median %.1f ms on the training thread, %.1f ms CPU drawing them", len(self.snapshot_ms),
                     np.median(self.snapshot_ms), np.median(self.server.draw_ms) if self.server.draw_ms else float("nan"))  # fmt: skip
            if self.camera_ms:
                log.info("viewer: %d of them early for a moved camera, median %.1f ms", len(self.camera_ms), np.median(self.camera_ms))

    def teardown(self, trainer, pl_module, stage: str) -> None:
        close(self.server, trainer.default_root_dir)

    # -- one snapshot ---------------------------------------------------------------------------
    def refresh(self, trainer, module: GaussianMapper, test_view: bool = True, cameras: dict[int, BrowserCamera] | None = None) -> None:
        """Take a snapshot now and hand it to the server: the Gaussians decoded for each of
        `cameras` (client id -> camera; None: every browser that reported one, and the shared
        Gaussians, every one as exported, when a browser has not or none were sent yet); with
        test_view, one held-out frame rendered for the panel's PSNR."""
        everyone = cameras is None
        cameras = self.server.browser_cameras() if everyone else cameras
        per_browser = splats_for_each(module, cameras)
        self._decoded.mark(cameras)
        splats = None
        if everyone and (not self._shared_sent or self.server.clients() > len(cameras)):
            splats = splats_for(module, None)
            self._shared_sent = splats is not None
        self._splats_id += 1
        views = module.training_views()
        for v in views:
            if v.kf_id not in self._thumbs:
                self._thumbs[v.kf_id] = thumbnail(v.image.numpy())
        keyframes = [KeyframeNode(v.kf_id, v.frame_index, v.w2c.numpy().astype(np.float64), v.camera, self._thumbs[v.kf_id])
                     for v in views]  # fmt: skip
        bridge = self.bridge
        points: MapPointLog | None = bridge.map_points if bridge is not None else None
        self.server.submit(Snapshot(
            splats=splats, splats_id=self._splats_id, splats_label=EVERY_ONE, per_browser=per_browser,
            points=None if points is None else points.points.copy(),
            point_colors=None if points is None else points.colors.copy(),
            trajectories=trajectories(self.sequence, bridge.run.trajectory(), self.align) if bridge is not None else None,
            keyframes=keyframes, panel=self._panel(trainer, module, test_view),
        ))  # fmt: skip

    def _panel(self, trainer, module: GaussianMapper, test_view: bool = True) -> dict[str, str]:
        counts, bridge = module.counts(), self.bridge
        step, now = trainer.global_step, time.perf_counter()
        rate = (step - self._last_step) / (now - self._t_step) if now > self._t_step and step > self._last_step else None
        self._last_step, self._t_step = step, now
        run = bridge.run if bridge is not None else None
        tracked = len(run.trajectory()) if run is not None else 0
        return {
            "run": "training",
            "step": f"{step} of {trainer.max_steps}",
            "test PSNR so far": self._test_psnr(module, step, test_view),
            "keyframes (training views)": f"{len(run.keyframe_frames()) if run else 0} ({counts.training_views})",
            "anchors": str(counts.anchors),
            "Gaussians": str(counts.gaussians),
            "map points": str(len(bridge.map_points) if bridge is not None else 0),
            "frames tracked": f"{tracked} of {len(self.sequence)}",
            "tracking": _fps(run.tracking_fps() if run is not None else None),
            "training": "n/a" if rate is None else f"{rate:.1f} steps/s",
            "frames dropped (live)": dropped(run) if run is not None else "n/a",
            "refresh": f"every {self.period():.0f} s",
        }

    def _test_psnr(self, module: GaussianMapper, step: int, render: bool = True) -> str:
        """Render (with render) one held-out test frame (in turn over test_views of them) at its
        estimated pose; the mean PSNR of the last test_views renders."""
        if self.cfg.test_views == 0:
            return "off (viewer.test_views=0)"
        test = self.bridge.run.test_frames() if self.bridge is not None and render else []
        if test:
            picks = np.asarray(test)[np.linspace(0, len(test) - 1, min(self.cfg.test_views, len(test))).round().astype(int)]
            index = int(picks[self._turn % len(picks)])
            self._turn += 1
            frame = self.sequence[index]
            render = module.render_image(self.bridge.run.trajectory()[index], frame.camera)["image"]
            self._test.append((index, psnr(render, torch.from_numpy(np.ascontiguousarray(frame.rgb))), step))
        if not self._test:
            return "n/a (no held-out frame tracked yet)"
        values = [p for _, p, _ in self._test]
        return f"{np.mean(values):.2f} dB ({len(values)} held-out frames, steps {self._test[0][2]}-{self._test[-1][2]})"

    def _selection(self, module: GaussianMapper, kf_id: int):
        view = next((v for v in module.training_views() if v.kf_id == kf_id), None)
        if view is None:
            return np.zeros((8, 8, 3), np.uint8), None, f"keyframe {kf_id} is not a training view"
        render = module.render_image(view.w2c, view.camera, view.kf_id)["image"]
        return view.image.numpy(), to_uint8(render).numpy(), f"keyframe {kf_id} (frame {view.frame_index}): image | render"


class TrackingViewer:
    """Serves the trajectory, keyframes and map points while segs.track runs: `tick()` after
    each frame takes a snapshot at most every refresh_s seconds while a browser is connected.
    run: the run's segs.pipeline RunState (trajectory, keyframes, map points)."""

    def __init__(self, cfg: ViewerConfig, sequence: Sequence, run, align: str):
        self.cfg, self.sequence, self.run, self.align = cfg, sequence, run, align
        self.server = start_server(cfg, f"segs.track: {getattr(sequence, 'name', '')}")
        self._last = -float("inf")
        self._t0 = time.perf_counter()

    def tick(self, frames_done: int, force: bool = False) -> None:
        self.server.serve_selection(self._selection)
        now = time.perf_counter()
        if not force and (now - self._last < self.cfg.refresh_s or not self.server.clients()):
            return
        self._last = now
        run, traj, points = self.run, self.run.trajectory(), self.run.map_points
        keyframes = [KeyframeNode(k, i, traj[i], self.sequence.camera) for k, i in sorted(run.keyframe_frames().items()) if i in traj]
        self.server.submit(Snapshot(
            points=points.points.copy(), point_colors=points.colors.copy(),
            trajectories=trajectories(self.sequence, traj, self.align), keyframes=keyframes,
            panel={"run": "tracking", "frames tracked": f"{len(traj)} of {len(self.sequence)} ({frames_done} processed)",
                   "lost frames": str(len(run.lost_frames())), "keyframes": str(len(keyframes)), "map points": str(len(points)),
                   "Gaussians": "0 (tracking only)", "tracking": _fps(frames_done / (now - self._t0) if now > self._t0 else None),
                   "frames dropped (live)": dropped(run)},
        ))  # fmt: skip

    def _selection(self, kf_id: int):
        index = self.run.keyframe_frames().get(kf_id)
        if index is None:
            return np.zeros((8, 8, 3), np.uint8), None, f"keyframe {kf_id} is no longer in the map"
        image = (np.clip(self.sequence[index].rgb, 0, 1) * 255 + 0.5).astype(np.uint8)
        return image, None, f"keyframe {kf_id} (frame {index}): image (tracking only: no map to render)"
