"""The Lightning callback between the SLAM frontend and the mapper (segs.modules).

Before each training step the bridge advances the run's frame source (segs.pipeline: frames fed
here, paced over the training steps, or tracked by a child process at its own pace), routes the
MapUpdate through the RunState (split, keyframe registry, map points) and pushes training views,
refreshed poses, new points and loop corrections into the mapper through
segs.modules.contract.GaussianMapper, the only part of the mapper it uses. Neither side imports
the other.
"""
from __future__ import annotations

import logging
from collections import OrderedDict
from dataclasses import dataclass

import lightning as L
import numpy as np
import torch
from tqdm import tqdm

from segs.callbacks.memory import MemoryGuard
from segs.data.frame import Frame
from segs.errors import TrackingFailed
from segs.map_points import MapPointLog
from segs.modules.contract import GaussianMapper, TrainingView, to_uint8
from segs.pipeline.legacy import bridge_state
from segs.pipeline.run_state import RunState
from segs.slam.base import STATE_FORMAT, MapUpdate

log = logging.getLogger(__name__)

WATCH_EVERY_FRAMES = 10  # memory check interval while tracking outside training steps


@dataclass
class _ViewData:
    """What a training view needs of a fed frame, kept compact until the frontend names its
    keyframes: image [H,W,3] uint8, depth [H,W] float32 (None when the mapper reads no depth)."""

    index: int
    timestamp: float
    camera: object
    image: torch.Tensor
    depth: torch.Tensor | None


class SlamBridge(L.Callback):
    """Plays the SLAM thread beside training.

    run: the RunState (sequence, frame source, split). feed_until: fraction of trainer.max_steps
    by which every frame has been fed to a paced (interleaved) frontend (the frames after the
    initial keyframes are spread evenly over those steps), as if the camera streamed in real time
    beside training; frames_per_step, when set, replaces it. A frontend in its own process
    (slam_mode=process | live) tracks at its own pace: the bridge only takes its MapUpdates
    before each step and waits for it at the end of training. min_initial_keyframes: mapping
    starts when the frontend has made this many keyframes. cache_frames: the latest fed frames
    kept for the training views of their keyframes (older ones are read again).
    """

    def __init__(self, run: RunState, feed_until: float, frames_per_step: float | None, min_initial_keyframes: int,
                 progress: bool, cache_frames: int):  # fmt: skip
        self.run, self.source, self.sequence = run, run.source, run.sequence
        self.feed_until, self.frames_per_step = feed_until, frames_per_step
        self.min_initial_keyframes, self.progress = min_initial_keyframes, progress
        self.credit = 0.0  # frames owed to a paced frontend
        self._cache: OrderedDict[int, _ViewData] = OrderedDict()  # the latest fed frames, by index
        self._cache_size = cache_frames
        self._keep_depth = True  # the mapper's uses_depth, read when training starts
        self._restored = False
        self._watch = None  # memory check called while tracking: where -> None (raises LimitError)
        self.source.on_frame = self._fed

    @property
    def map_points(self) -> MapPointLog:
        """Every SLAM map point handed over (map_points.ply, the viewer)."""
        return self.run.map_points

    # -- Lightning hooks ------------------------------------------------------------------------
    def on_train_start(self, trainer, pl_module: GaussianMapper) -> None:
        self._keep_depth = pl_module.uses_depth
        guard = next((c for c in trainer.callbacks if isinstance(c, MemoryGuard)), None)
        if guard is not None:  # nothing trained before mapping starts (after fit: final.ckpt exists)
            self._watch = lambda where: guard.check(trainer, where, save=False)
        if self._restored:
            return
        source = self.source
        bar = tqdm(total=len(self.sequence), desc="tracking until mapping starts", disable=not self.progress, leave=False)
        # also wait for the first map points: the ORB frontend hands them over once they have
        # survived culling over a few keyframes
        while not source.exhausted() and (
            len(source.keyframe_frames()) < self.min_initial_keyframes or self._empty(pl_module.counts())
        ):
            self._push(source.track(1, timeout=0.1), pl_module)
            bar.update(source.cursor - bar.n)
        bar.close()
        if source.exhausted():
            self._push(self.run.finish(), pl_module)
        if source.paced and self.frames_per_step is None:
            steps = max(self.feed_until * (trainer.max_steps or 1), 1.0)
            self.frames_per_step = source.remaining() / steps
        self._check_mappable(pl_module)

    def _check_mappable(self, pl_module: GaussianMapper) -> None:
        """Raise TrackingFailed when the frames so far gave nothing to train on."""
        name, lost = getattr(self.sequence, "name", "the sequence"), len(self.run.lost_frames())
        counts = pl_module.counts()
        if counts.training_views == 0:
            reason = f"no training keyframe in the {len(self.sequence)} frames of {name} ({lost} frames could not be tracked)"
        elif counts.gaussians == 0:  # keyframes, but not one 3D point (tiny or blank images)
            reason = f"the frontend gave no 3D point in {counts.training_views} keyframes of {name} (image too small or without texture?)"
        else:
            return
        raise TrackingFailed(f"data: {reason}; nothing to map", frames=len(self.sequence), lost=lost)

    @staticmethod
    def _empty(counts) -> bool:
        """Nothing to train on yet: no training view or no Gaussian."""
        return counts.training_views == 0 or counts.gaussians == 0

    def on_train_batch_start(self, trainer, pl_module: GaussianMapper, batch, batch_idx) -> None:
        frames = 0
        if self.source.paced:  # the frames this step owes the camera
            self.credit += self.frames_per_step
            while self.credit >= 1.0 and frames < self.source.remaining():
                frames += 1
                self.credit -= 1.0
        update = self.source.track(frames)
        if self.source.exhausted() and not self.run.finished:
            update = update.merge(self.run.finish())
        self._push(update, pl_module)

    # -- feeding --------------------------------------------------------------------------------
    def _fed(self, frame: Frame, result) -> None:
        """After each frame tracked in this process: kept (compact) for its keyframe's view; memory check."""
        self._cache[frame.index] = self._view_data(frame)
        while len(self._cache) > self._cache_size:
            self._cache.popitem(last=False)
        if self._watch is not None and self.source.cursor % WATCH_EVERY_FRAMES == 0:
            self._watch(f"while tracking frame {frame.index}")

    def complete_sequence(self) -> None:
        """Track the frames not fed yet (training stopped early) so every frame gets a pose; their
        updates are superseded by the final poses (the mapper is not trained any more)."""
        if self.run.finished:
            return
        source = self.source
        bar = tqdm(total=source.remaining(), desc="tracking the rest", disable=not self.progress, leave=False)
        start = source.cursor
        while not source.exhausted():
            self.map_points.add(source.track(source.remaining(), timeout=0.1))
            bar.update(source.cursor - start - bar.n)
        bar.close()
        self.map_points.add(source.track(0))
        self.map_points.add(self.run.finish())

    def _view_data(self, frame: Frame) -> _ViewData:
        depth = torch.from_numpy(frame.depth.astype(np.float32)) if frame.depth is not None and self._keep_depth else None
        return _ViewData(frame.index, frame.timestamp, frame.camera, to_uint8(torch.from_numpy(np.ascontiguousarray(frame.rgb))), depth)

    def _frame_data(self, index: int) -> _ViewData:
        return self._cache[index] if index in self._cache else self._view_data(self.sequence[index])

    def _push(self, update: MapUpdate, module: GaussianMapper) -> None:
        """Hand one MapUpdate to the mapper, routed by the RunState; every pose is converted once
        (float32 copies) and a new view's pose is registered once, with the view."""
        routed = self.run.route(update)
        if routed is None:
            return
        f32 = lambda v: torch.tensor(v, dtype=torch.float32)  # noqa: E731
        poses = {int(k): f32(v) for k, v in routed.poses.items()}
        new = [self._training_view(kf_id, self._frame_data(idx), f32(w2c)) for kf_id, idx, w2c in routed.views]
        if new:
            module.add_keyframes(new)
        if poses:
            module.update_poses(poses)
        if routed.corrections:
            module.correct_map({int(k): f32(v) for k, v in routed.corrections.items()})
        if len(routed.points):
            module.add_points(
                torch.as_tensor(routed.points, dtype=torch.float32),
                torch.as_tensor(routed.colors, dtype=torch.float32),
                torch.as_tensor(routed.point_kf, dtype=torch.int64),
            )

    @staticmethod
    def _training_view(kf_id: int, data: _ViewData, w2c: torch.Tensor) -> TrainingView:
        return TrainingView(kf_id=kf_id, frame_index=data.index, timestamp=data.timestamp, image=data.image, w2c=w2c,
                            camera=data.camera, depth=data.depth)  # fmt: skip

    # -- checkpoints ----------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {"format": STATE_FORMAT, "run": self.run.state_dict(), "credit": self.credit,
                "frames_per_step": self.frames_per_step}  # fmt: skip

    def load_state_dict(self, state: dict) -> None:
        state = bridge_state(state)
        self.run.load_state_dict(state["run"])
        self.credit, self.frames_per_step = float(state["credit"]), state["frames_per_step"]
        self._restored = True
