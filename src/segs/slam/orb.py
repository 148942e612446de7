"""OrbFrontend: the ORB-SLAM style frontend (tracking, local mapping, loop closing) as a `Frontend`.

Single-thread mode (default, deterministic): `process` tracks the frame and, when it becomes a
keyframe, runs local mapping and loop closing before returning. Threaded mode: local mapping and
loop closing run in a background thread fed by a keyframe queue; tracking stays in the caller's
thread; the map is shared under an RLock (bundle adjustment optimises outside it).

The frontend builds and wires the parts (docs/architecture.md, `segs.slam`): `Tracker` (owns the
per-frame pose record `FramePoses`), `KeyFrameQueue` (hands keyframes to mapping), `LocalMapper`,
`LoopCloser`, sharing the `Map`, the keyframe database and the `MapOutbox`; each gets what it uses
in its constructor and none of them sees this class.

What the mapper receives (MapUpdate via poll): keyframes once local mapping processed them, the
poses of the keyframes each local BA touched (all of them after a loop closure and at finish),
map points once they survived the recent-point culling (tagged with their creating keyframe), and
loop corrections. Every frame's pose is kept relative to its reference keyframe and recomposed
with the latest keyframe poses by `trajectory()`.
"""
from __future__ import annotations

import logging
import time
from typing import Any, Callable, Mapping

import numpy as np

from segs.data.frame import Camera, Frame
from segs.errors import ConfigError
from segs.slam import config as C
from segs.slam import orb_state
from segs.slam.backend.ba_process import BundleAdjusterProcess
from segs.slam.base import FrameResult, Frontend, MapUpdate
from segs.slam.features.extractor import OrbExtractor
from segs.slam.features.frame import FrameBuilder, SlamFrame
from segs.slam.backend.keyframe_queue import KeyFrameQueue
from segs.slam.backend.local_mapping import LocalMapper
from segs.slam.backend.loop_closing import LoopCloser
from segs.slam.map.map import KeyFrame, Map
from segs.slam.estimation.optimize import BundleAdjuster
from segs.slam.outbox import MapOutbox
from segs.slam.sensor import SensorSetup
from segs.slam.features.stereo import StereoMatcher
from segs.slam.tracking.tracker import Tracker
from segs.slam.map.vocabulary import KeyFrameDatabase, Vocabulary

log = logging.getLogger(__name__)


class OrbFrontend(Frontend):
    """ORB-SLAM style frontend for "mono", "stereo" and "rgbd" sequences.

    camera: intrinsics of the (undistorted / rectified) images; sensor: "mono" | "stereo" | "rgbd";
    features, tracking, init, local_mapping, loop, matching: parameter groups (mappings with every
    key of conf/slam/orb.yaml's, typed by segs.slam.config.OrbConfig); threaded: mapping in a
    background thread; seed: RANSAC seeds; final_global_ba: a global bundle adjustment in finish();
    verbose: log events. segs.config.slam_frontend builds one from the YAML.
    """

    def __init__(self, camera: Camera, sensor: str, *, features: Mapping, tracking: Mapping, init: Mapping,
                 local_mapping: Mapping, loop: Mapping, matching: Mapping, threaded: bool, seed: int,
                 final_global_ba: bool, verbose: bool):  # fmt: skip
        if sensor not in ("mono", "stereo", "rgbd"):
            raise ConfigError(f"slam: unknown sensor {sensor!r} (mono, stereo, rgbd)")
        if sensor == "stereo" and not camera.baseline:
            raise ConfigError("slam: stereo needs camera.baseline (metres) of the rectified pair")

        self.cfg: C.OrbConfig = C.build_frontend_config(C.OrbConfig, {
            "threaded": threaded, "seed": seed, "final_global_ba": final_global_ba, "verbose": verbose,
            "features": features, "tracking": tracking, "init": init, "local_mapping": local_mapping, "loop": loop,
            "matching": matching})  # fmt: skip
        self.camera, self.sensor, self.seed = camera, sensor, self.cfg.seed
        self.threaded, self.final_global_ba, self.verbose = self.cfg.threaded, self.cfg.final_global_ba, self.cfg.verbose
        fc, tc = self.cfg.features, self.cfg.tracking
        baseline = camera.baseline if sensor == "stereo" else tc.rgbd_baseline
        bf = float(camera.fx * baseline)
        self.extractor = OrbExtractor.from_config(fc)
        scales = self.extractor.scales
        self.setup = SensorSetup(
            camera, sensor, camera.K, bf, th_depth=tc.close_depth_factor * baseline,
            # RGB-D depth noise sigma_z = k z^2 is a constant sigma of the virtual right coordinate
            ur_sigma=bf * tc.rgbd_depth_noise if sensor == "rgbd" else None,
            scales=scales, sigma2=self.extractor.sigma2, scale_factor=fc.scale_factor, n_features=fc.n_features)
        stereo = StereoMatcher(bf, scales, min_depth=baseline) if sensor == "stereo" else None
        self.builder = FrameBuilder(camera, sensor, self.extractor, bf, tc.max_depth, stereo, fc.grid_cell,
                                    tc.depth_edge_ratio)
        self.vocab = Vocabulary.load(self.cfg.loop.vocabulary)
        if self.cfg.local_mapping.triangulate_node_level > len(self.vocab.levels):
            raise ConfigError(f"slam.local_mapping.triangulate_node_level: at most the vocabulary's depth "
                              f"{len(self.vocab.levels)}; got {self.cfg.local_mapping.triangulate_node_level}")
        # threaded: bundle adjustment in a child process (gtsam holds the GIL while optimising)
        self.ba = (BundleAdjusterProcess if self.threaded else BundleAdjuster)(
            camera.K, bf if sensor != "mono" else 0.0, scales, ur_sigma=self.setup.ur_sigma)
        self.keyframes = KeyFrameQueue(self._map_keyframe, self.threaded)
        self._log = log.info if self.verbose else log.debug
        self._wire(Map(scales), KeyFrameDatabase(), MapOutbox())
        # seconds per frame: features (ORB, depth / stereo), track (features + tracking; wall clock
        # and process CPU time); per keyframe: mapping (local mapping incl. BA), loop (closing)
        self.times: dict[str, list[float]] = {"features": [], "track": [], "track_cpu": [], "mapping": [],
                                              "loop": []}

    def _wire(self, map_: Map, kfdb: KeyFrameDatabase, outbox: MapOutbox) -> None:
        """The components around one map (a new one, or a checkpoint's), each given what it uses."""
        self.map, self.kfdb, self.outbox = map_, kfdb, outbox
        cfg, setup = self.cfg, self.setup
        self.local_mapping = LocalMapper(cfg.local_mapping, cfg.matching, setup, map_, self.vocab, kfdb, self.ba, outbox, self._log)
        self.tracker = Tracker(cfg.tracking, cfg.init, cfg.matching, setup, map_, self.vocab, kfdb, self.local_mapping, outbox,
                               self.keyframes, self.seed, self._log)
        self.loop = LoopCloser(cfg.loop, setup, map_, kfdb, self.local_mapping, outbox, self.tracker.on_map_corrected,
                               self.seed, self._log)

    # ------------------------------------------------------------------ Frontend API
    def prepare(self, frame: Frame) -> SlamFrame:
        """The frame's features (ORB, depth / stereo) as a SlamFrame, built ahead by a frame
        source in its own thread or process; the build's wall and thread CPU seconds are kept on it."""
        return self.builder.timed_build(frame)

    def preparer(self) -> Callable[[Frame], SlamFrame]:
        """prepare() as a picklable callable (the frame builder's), for a reader process."""
        return self.builder.timed_build

    def process(self, frame: Frame | SlamFrame) -> FrameResult:
        """Track a frame; its features are built here unless prepare() built them ahead ("track"
        counts their time either way, so it stays the per-frame cost)."""
        self.keyframes.raise_error()
        t0, c0 = time.perf_counter(), time.process_time()
        if isinstance(frame, SlamFrame):
            sf, (build_s, build_cpu) = frame, frame.build_seconds
            t0, c0 = t0 - build_s, c0 - build_cpu
        else:
            sf = self.builder.build(frame)
            build_s = time.perf_counter() - t0
        kf = self.tracker.track(sf)
        self.times["features"].append(build_s)
        self.times["track"].append(time.perf_counter() - t0)
        self.times["track_cpu"].append(time.process_time() - c0)
        if sf.w2c is None:
            return FrameResult(frame.index, None)
        if kf is not None:
            self.keyframes.submit(kf)
        return FrameResult(frame.index, sf.w2c.copy(), kf.kf_id if kf is not None else None)

    def poll(self) -> MapUpdate:
        self.keyframes.raise_error()
        return self.outbox.take()

    def finish(self) -> MapUpdate:
        self.keyframes.stop()
        if self.final_global_ba and len(self.map.kfs) > 1:
            with self.map.lock:
                self.loop.run_global_ba(self.cfg.loop.global_ba_iterations)
        with self.map.lock:
            self.local_mapping.flush_recent()
            self.outbox.add_poses(self.map.keyframe_poses(list(self.map.kfs) + list(self.map.culled)))
        if isinstance(self.ba, BundleAdjusterProcess):
            self.ba.close()  # restarted on demand
        return self.poll()

    def trajectory(self) -> dict[int, np.ndarray]:
        with self.map.lock:
            return self.tracker.poses.trajectory(self.map.kf_pose)

    def lost_frames(self) -> list[int]:
        return self.tracker.poses.lost_frames()

    def keyframe_frames(self) -> dict[int, int]:
        with self.map.lock:
            return self.tracker.poses.keyframe_frames(self.map.kfs)

    def state_dict(self) -> dict:
        """The map, keyframe database, outbox and components' state fields as arrays and dicts
        (segs.slam.orb_state; format segs.state.v3). Stops the mapping thread."""
        self.keyframes.stop()
        with self.map.lock:
            return orb_state.encode({"map": self.map, "kfdb": self.kfdb, "outbox": self.outbox,
                                     "tracker": self.tracker.state_fields(),
                                     "local_mapping": self.local_mapping.state_fields(), "loop": self.loop.state_fields()})  # fmt: skip

    def load_state_dict(self, state: dict) -> None:
        """A state of `state_dict`, or of the pickled formats before it ("segs.orb.v1" / "v2",
        converted by segs.slam.orb_state); the frontend keeps its own configuration."""
        parts = orb_state.decode(state)
        self.keyframes.stop()
        self._wire(parts["map"], parts["kfdb"], parts["outbox"])
        for name in ("tracker", "local_mapping", "loop"):
            getattr(self, name).load_state_dict(parts[name])

    # ------------------------------------------------------------------ mapping of a keyframe
    def _map_keyframe(self, kf: KeyFrame) -> None:
        """Local mapping, then loop closing of a new keyframe (in the mapping thread if threaded)."""
        t0 = time.perf_counter()
        self.local_mapping.process(kf)
        with self.map.lock:
            if kf.kf_id in self.map.kfs:
                self.outbox.add_keyframe(kf.kf_id, kf.w2c)
        t1 = time.perf_counter()
        self.loop.process(kf)
        t2 = time.perf_counter()
        self.times["mapping"].append(t1 - t0)
        self.times["loop"].append(t2 - t1)

    def accepts_keyframes(self) -> bool:
        return self.keyframes.accepts_keyframes()

    def mapping_idle(self) -> bool:
        return self.keyframes.idle()

    # ------------------------------------------------------------------ statistics
    def stats(self) -> dict[str, Any]:
        t = {k: np.array(v) for k, v in self.times.items()}
        return {
            "frames": len(self.tracker.poses) + len(self.lost_frames()),
            "tracked": len(self.tracker.poses),
            "lost": len(self.lost_frames()),
            "keyframes": len(self.map.kfs),
            "culled_keyframes": len(self.map.culled),
            "points": int(self.map.valid[: self.map.n].sum()),
            "loops": len(self.loop.loops),
            "depth_retries": len(self.tracker.depth_retries),
            "track_ms_median": float(np.median(t["track"]) * 1e3) if len(t["track"]) else float("nan"),
            "mapping_ms_median": float(np.median(t["mapping"]) * 1e3) if len(t["mapping"]) else float("nan"),
            "local_ba_ms_median": float(np.median(self.local_mapping.ba_times) * 1e3) if self.local_mapping.ba_times else float("nan"),
        }
