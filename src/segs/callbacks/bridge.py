"""The one bridge between the SLAM frontend (segs.slam) and the mapper (segs.modules).

Before each training step the bridge feeds the frames that became available to the frontend,
polls its MapUpdate and pushes training views, refreshed poses, new points and loop corrections
into the mapper through segs.modules.contract.GaussianMapper, the only part of the mapper it
uses. Neither side imports the other.
"""
from __future__ import annotations

import logging
import time
from collections import OrderedDict
from dataclasses import dataclass

import lightning as L
import numpy as np
import torch
from tqdm import tqdm

from segs.callbacks.memory import MemoryGuard
from segs.data.frame import Frame, Sequence
from segs.errors import TrackingFailed
from segs.map_points import MapPointLog
from segs.modules.contract import GaussianMapper, TrainingView, to_uint8
from segs.slam.base import Frontend, MapUpdate
from segs.slam.runtime.process import FrontendProcess

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

    feed_until: fraction of trainer.max_steps by which every frame has been fed to the frontend
        (the frames after the initial keyframes are spread evenly over those steps), as if the
        camera streamed in real time beside training; frames_per_step, when set, replaces it.
    min_initial_keyframes: mapping starts when the frontend has made this many keyframes.
    holdout_every: frames with index % n == 0 never become training views, and the map points
        their keyframes create never reach the mapper (counted in held_out_points); 0 = off.

    With a FrontendProcess (slam_mode=process | live) the frontend reads and tracks the frames in
    its own process, beside training: the bridge only polls its MapUpdates before each step
    (feed_until / frames_per_step do not apply), and waits for it at the end of training.
    """

    def __init__(self, sequence: Sequence, frontend: Frontend, feed_until: float = 0.2,
                 frames_per_step: float | None = None, min_initial_keyframes: int = 10,
                 holdout_every: int = 0, progress: bool = True, cache_frames: int = 64):  # fmt: skip
        self.sequence, self.frontend = sequence, frontend
        self.feed_until, self.frames_per_step = feed_until, frames_per_step
        self.min_initial_keyframes = min_initial_keyframes
        self.holdout_every, self.progress = holdout_every, progress
        self.cursor = 0  # next frame index to feed
        self.credit = 0.0
        self.finished = False
        self.trained_frames: dict[int, int] = {}  # kf_id -> frame index of views the module trains on
        self.held_out_keyframes: list[int] = []
        self._cache: OrderedDict[int, _ViewData] = OrderedDict()  # the latest fed frames, by index
        self._cache_size = cache_frames
        self._keep_depth = True  # the mapper's uses_depth, read when training starts
        self._restored = False
        self.process_seconds = 0.0
        self.processed = 0
        self.held_out_points = 0  # SLAM points created by held-out keyframes, never given to the mapper
        self._watch = None  # memory check called while tracking: where -> None (raises LimitError)
        self.map_points = MapPointLog()  # every SLAM map point handed over (map_points.ply, the viewer)
        self.in_process = isinstance(frontend, FrontendProcess)

    # -- Lightning hooks ------------------------------------------------------------------------
    def on_train_start(self, trainer, pl_module: GaussianMapper) -> None:
        self._keep_depth = pl_module.uses_depth
        guard = next((c for c in trainer.callbacks if isinstance(c, MemoryGuard)), None)
        if guard is not None:  # nothing trained before mapping starts (after fit: final.ckpt exists)
            self._watch = lambda where: guard.check(trainer, where, save=False)
        if self._restored:
            return
        if self.in_process:
            self._start_process(pl_module)
            return
        bar = tqdm(total=len(self.sequence), desc="tracking until mapping starts", disable=not self.progress, leave=False)
        # also wait for the first map points: the ORB frontend hands them over once they have
        # survived culling over a few keyframes
        while self.cursor < len(self.sequence) and (
            len(self.frontend.keyframe_frames()) < self.min_initial_keyframes or self._empty(pl_module.counts())
        ):
            self._feed_one()
            self._push(self.frontend.poll(), pl_module)
            bar.update(1)
        bar.close()
        if self.cursor >= len(self.sequence):
            self._push(self._finish(), pl_module)
        if self.frames_per_step is None:
            steps = max(self.feed_until * (trainer.max_steps or 1), 1.0)
            self.frames_per_step = (len(self.sequence) - self.cursor) / steps
        self._check_mappable(pl_module)

    def _start_process(self, pl_module: GaussianMapper) -> None:
        """Start the frontend process and wait for the initial keyframes and points."""
        fe: FrontendProcess = self.frontend
        bar = tqdm(total=len(self.sequence), desc="tracking until mapping starts", disable=not self.progress, leave=False)
        while not fe.done() and (len(fe.keyframe_frames()) < self.min_initial_keyframes or self._empty(pl_module.counts())):
            self._push(fe.poll(timeout=0.1), pl_module)
            bar.update(fe.cursor - bar.n)
        bar.close()
        if fe.done():
            self._push(self._finish(), pl_module)
        self._check_mappable(pl_module)

    def _check_mappable(self, pl_module: GaussianMapper) -> None:
        """Raise TrackingFailed when the frames so far gave nothing to train on."""
        name, lost = getattr(self.sequence, "name", "the sequence"), len(self.frontend.lost_frames())
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
        if self.in_process:
            update = self.frontend.poll()
            self.cursor = self.frontend.cursor
            if self.frontend.done() and not self.finished:
                update = update.merge(self._finish())
            self._push(update, pl_module)
            return
        self.credit += self.frames_per_step
        update = MapUpdate()
        while self.credit >= 1.0 and self.cursor < len(self.sequence):
            self._feed_one()
            self.credit -= 1.0
        if self.cursor >= len(self.sequence) and not self.finished:
            update = update.merge(self.frontend.poll()).merge(self._finish())
        else:
            update = update.merge(self.frontend.poll())
        self._push(update, pl_module)

    # -- feeding --------------------------------------------------------------------------------
    def _feed_one(self) -> None:
        frame = self.sequence[self.cursor]
        self._cache[frame.index] = self._view_data(frame)
        while len(self._cache) > self._cache_size:
            self._cache.popitem(last=False)
        t0 = time.perf_counter()
        self.frontend.process(frame)
        self.process_seconds += time.perf_counter() - t0
        self.processed += 1
        self.cursor += 1
        if self._watch is not None and self.cursor % WATCH_EVERY_FRAMES == 0:
            self._watch(f"while tracking frame {frame.index}")

    def _finish(self) -> MapUpdate:
        self.finished = True
        update = self.frontend.finish()
        # after SLAM ends every keyframe pose is replaced by the final optimised trajectory
        traj = self.frontend.trajectory()
        for kf_id, idx in self.frontend.keyframe_frames().items():
            if idx in traj:
                update.poses.setdefault(kf_id, traj[idx])
        return update

    def complete_sequence(self) -> None:
        """Track the frames not fed yet (training stopped early) so every frame gets a pose."""
        if self.finished:
            return
        bar = tqdm(total=len(self.sequence) - self.cursor, desc="tracking the rest", disable=not self.progress, leave=False)
        if self.in_process:  # its updates are superseded by the final poses, as below
            while not self.frontend.done():
                self.map_points.add(self.frontend.poll(timeout=0.1))
                bar.update(self.frontend.cursor - self.cursor)
                self.cursor = self.frontend.cursor
        while self.cursor < len(self.sequence):
            self._feed_one()
            bar.update(1)
        bar.close()
        self.map_points.add(self.frontend.poll())
        self.map_points.add(self._finish())

    def _view_data(self, frame: Frame) -> _ViewData:
        depth = torch.from_numpy(frame.depth.astype(np.float32)) if frame.depth is not None and self._keep_depth else None
        return _ViewData(frame.index, frame.timestamp, frame.camera, to_uint8(torch.from_numpy(np.ascontiguousarray(frame.rgb))), depth)

    def _frame_data(self, index: int) -> _ViewData:
        return self._cache[index] if index in self._cache else self._view_data(self.sequence[index])

    def _push(self, update: MapUpdate, module: GaussianMapper) -> None:
        """Hand one MapUpdate to the mapper; every pose is converted once (float32 copies) and a
        new view's pose is registered once, with the view."""
        if update.is_empty():
            return
        self.map_points.add(update)
        kf_frames = self.frontend.keyframe_frames()
        poses = {int(k): torch.tensor(v, dtype=torch.float32) for k, v in update.poses.items()}
        new = []
        for kf_id in update.new_keyframes:
            idx = kf_frames.get(kf_id)
            if idx is None or kf_id not in poses:
                continue
            if self.holdout_every and idx % self.holdout_every == 0:
                self.held_out_keyframes.append(kf_id)
                continue
            new.append(self._training_view(kf_id, self._frame_data(idx), poses.pop(kf_id)))
            self.trained_frames[kf_id] = idx
        if new:
            module.add_keyframes(new)
        if poses:
            module.update_poses(poses)
        if update.corrections:
            module.correct_map({int(k): torch.tensor(v, dtype=torch.float32) for k, v in update.corrections.items()})
        keep = self._mappable_points(update.point_kf, kf_frames)
        if keep.any():
            module.add_points(
                torch.as_tensor(update.points[keep], dtype=torch.float32),
                torch.as_tensor(update.colors[keep], dtype=torch.float32),
                torch.as_tensor(update.point_kf[keep], dtype=torch.int64),
            )

    def _mappable_points(self, point_kf: np.ndarray, kf_frames: dict[int, int]) -> np.ndarray:
        """[M] bool: points not created by a held-out keyframe (their depth / colour come from a
        test frame, which the map must not see); the others are counted in held_out_points."""
        held = set(self.held_out_keyframes)
        if self.holdout_every:
            held |= {k for k, i in kf_frames.items() if i % self.holdout_every == 0}
        keep = ~np.isin(np.asarray(point_kf, dtype=np.int64), np.fromiter(held, np.int64, len(held)))
        self.held_out_points += int((~keep).sum())
        return keep

    @staticmethod
    def _training_view(kf_id: int, data: _ViewData, w2c: torch.Tensor) -> TrainingView:
        return TrainingView(kf_id=kf_id, frame_index=data.index, timestamp=data.timestamp, image=data.image, w2c=w2c,
                            camera=data.camera, depth=data.depth)  # fmt: skip

    def write_partial_trajectory(self, path) -> None:
        """The estimated trajectory so far (TUM format), e.g. when training is interrupted."""
        from segs.trajectory import estimated_c2w, write_tum

        idx, c2w = estimated_c2w(self.frontend.trajectory())
        write_tum(path, self.sequence.timestamps[idx], c2w)

    def tracking_fps(self) -> float | None:
        """Frames per second of frontend.process (tracking and, single-threaded, local mapping)."""
        if self.in_process:  # the child's own time in process()
            fe = self.frontend
            return fe.frames_done / fe.process_seconds if fe.process_seconds > 0 else None
        return self.processed / self.process_seconds if self.process_seconds > 0 else None

    # -- results --------------------------------------------------------------------------------
    def test_frames(self) -> list[int]:
        """Tracked frames whose images were never trained on (the paper's test views)."""
        trained = set(self.trained_frames.values())
        return sorted(i for i in self.frontend.trajectory() if i not in trained)

    # -- checkpoints ----------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {
            "cursor": self.cursor,
            "credit": self.credit,
            "frames_per_step": self.frames_per_step,
            "finished": self.finished,
            "trained_frames": dict(self.trained_frames),
            "held_out_keyframes": list(self.held_out_keyframes),
            "held_out_points": self.held_out_points,
            "process_seconds": self.process_seconds,
            "processed": self.processed,
            "frontend": self.frontend.state_dict(),
            "map_points": self.map_points.state_dict(),
        }

    def load_state_dict(self, state: dict) -> None:
        self.cursor, self.credit, self.finished = state["cursor"], state["credit"], state["finished"]
        self.frames_per_step = state["frames_per_step"]
        self.trained_frames = {int(k): int(v) for k, v in state["trained_frames"].items()}
        self.held_out_keyframes = list(state["held_out_keyframes"])
        self.held_out_points = int(state.get("held_out_points", 0))
        # tracking speed over every session (checkpoints older than this field: this session only)
        self.process_seconds, self.processed = float(state.get("process_seconds", 0.0)), int(state.get("processed", 0))
        self.frontend.load_state_dict(state["frontend"])
        if "map_points" in state:  # checkpoints older than map_points.ply: the points of this session only
            self.map_points.load_state_dict(state["map_points"])
        self._restored = True
