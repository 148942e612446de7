"""OrbFrontend: the ORB-SLAM style frontend (tracking, local mapping, loop closing) as a `Frontend`.

Single-thread mode (default, deterministic): `process` tracks the frame and, when it becomes a
keyframe, runs local mapping and loop closing before returning. Threaded mode: local mapping and
loop closing run in a background thread fed by a keyframe queue; tracking stays in the caller's
thread; the map is shared under an RLock (bundle adjustment optimises outside it).

What the mapper receives (MapUpdate via poll): keyframes once local mapping processed them, the
poses of the keyframes each local BA touched (all of them after a loop closure and at finish),
map points once they survived the recent-point culling (tagged with their creating keyframe), and
loop corrections. Every frame's pose is kept relative to its reference keyframe and recomposed
with the latest keyframe poses by `trajectory()`.
"""
from __future__ import annotations

import logging
import pickle
import queue
import threading
import time
from types import SimpleNamespace
from typing import Any, Mapping

import numpy as np

from segs.data.frame import Camera, Frame
from segs.errors import ConfigError
from segs.slam import config as C
from segs.slam.ba_process import BundleAdjusterProcess
from segs.slam.base import FrameResult, Frontend, MapUpdate
from segs.slam.features import OrbExtractor
from segs.slam.frame import FrameBuilder
from segs.slam.geometry import inv_se3
from segs.slam.local_mapping import LocalMapper
from segs.slam.loop_closing import LoopCloser
from segs.slam.map import KeyFrame, Map
from segs.slam.optimize import BundleAdjuster
from segs.slam.stereo import StereoMatcher
from segs.slam.tracking import Tracker
from segs.slam.vocabulary import KeyFrameDatabase, Vocabulary

log = logging.getLogger(__name__)


class OrbFrontend(Frontend):
    """ORB-SLAM style frontend for "mono", "stereo" and "rgbd" sequences.

    camera: intrinsics of the (undistorted / rectified) images; sensor: "mono" | "stereo" | "rgbd";
    features, tracking, init, mapping, loop: parameter groups (see segs.slam.config and
    conf/slam/orb.yaml); threaded: mapping in a background thread; seed: RANSAC seeds;
    final_global_ba: a global bundle adjustment in finish(); verbose: log events.
    """

    def __init__(self, camera: Camera, sensor: str, features: Mapping | None = None,
                 tracking: Mapping | None = None, init: Mapping | None = None,
                 mapping: Mapping | None = None, loop: Mapping | None = None, threaded: bool = False,
                 seed: int = 0, final_global_ba: bool = False, verbose: bool = False):
        if sensor not in ("mono", "stereo", "rgbd"):
            raise ConfigError(f"slam: unknown sensor {sensor!r} (mono, stereo, rgbd)")
        if sensor == "stereo" and not camera.baseline:
            raise ConfigError("slam: stereo needs camera.baseline (metres) of the rectified pair")

        self.cfg = SimpleNamespace()
        for name, group in (("features", features), ("tracking", tracking), ("init", init),
                            ("mapping", mapping), ("loop", loop)):
            setattr(self.cfg, name, C.build(C.GROUPS[name], group, name))
        self.camera, self.sensor, self.seed = camera, sensor, int(seed)
        self.threaded, self.final_global_ba, self.verbose = bool(threaded), bool(final_global_ba), bool(verbose)
        self.K = camera.K
        fc, tc = self.cfg.features, self.cfg.tracking
        baseline = camera.baseline if sensor == "stereo" else tc.rgbd_baseline
        self.bf = float(camera.fx * baseline)
        self.th_depth = tc.close_depth_factor * baseline
        # RGB-D depth noise sigma_z = k z^2 is a constant sigma of the virtual right coordinate
        self.ur_sigma = self.bf * tc.rgbd_depth_noise if sensor == "rgbd" else None
        self.extractor = OrbExtractor(fc.n_features, fc.scale_factor, fc.n_levels, fc.fast_threshold,
                                      fc.min_fast_threshold, fc.cell_size, fc.oversample)
        self.scales, self.sigma2 = self.extractor.scales, self.extractor.sigma2
        self.scale_factor = fc.scale_factor
        stereo = StereoMatcher(self.bf, self.scales, min_depth=baseline) if sensor == "stereo" else None
        self.builder = FrameBuilder(camera, sensor, self.extractor, self.bf, tc.max_depth, stereo, fc.grid_cell,
                                    tc.depth_edge_ratio)
        self.vocab = Vocabulary.load(self.cfg.loop.vocabulary)
        # threaded: bundle adjustment in a child process (gtsam holds the GIL while optimising)
        self.ba = (BundleAdjusterProcess if self.threaded else BundleAdjuster)(
            self.K, self.bf if sensor != "mono" else 0.0, self.scales, ur_sigma=self.ur_sigma)
        self._out_lock = threading.Lock()
        self._reset_state()
        self._queue: queue.Queue | None = None
        self._worker: threading.Thread | None = None
        self._worker_error: BaseException | None = None
        self._busy = False
        # seconds per frame: features (ORB, depth / stereo), track (features + tracking; wall clock
        # and process CPU time); per keyframe: mapping (local mapping incl. BA), loop (closing)
        self.times: dict[str, list[float]] = {"features": [], "track": [], "track_cpu": [], "mapping": [],
                                              "loop": []}

    def _reset_state(self) -> None:
        self.map = Map(self.scales)
        self.kfdb = KeyFrameDatabase()
        self.mapper = LocalMapper(self)
        self.loop = LoopCloser(self)
        self.tracker = Tracker(self)
        self._traj: dict[int, tuple] = {}
        self._lost: set[int] = set()
        self._pending = MapUpdate()
        self._pending_pids: list[np.ndarray] = []
        self._kf_frames: dict[int, int] = {}

    # ------------------------------------------------------------------ Frontend API
    def process(self, frame: Frame) -> FrameResult:
        self._raise_worker_error()
        t0, c0 = time.perf_counter(), time.process_time()
        sf = self.builder.build(frame)
        t1 = time.perf_counter()
        kf = self.tracker.track(sf)
        self.times["features"].append(t1 - t0)
        self.times["track"].append(time.perf_counter() - t0)
        self.times["track_cpu"].append(time.process_time() - c0)
        if sf.w2c is None:
            self._lost.add(frame.index)
            return FrameResult(frame.index, None)
        with self.map.lock:
            if kf is not None:
                self._traj[frame.index] = ("kf", kf.kf_id)
                self._kf_frames[kf.kf_id] = frame.index
            else:
                ref = sf.ref_kf
                base = self.map.kf_pose(ref) if ref is not None else None
                if base is None:  # no reference keyframe (cannot happen after initialization)
                    self._traj[frame.index] = ("abs", None, sf.w2c.copy())
                else:
                    self._traj[frame.index] = ("rel", ref, sf.w2c @ inv_se3(base))
        if kf is not None:
            self._dispatch(kf)
        return FrameResult(frame.index, sf.w2c.copy(), kf.kf_id if kf is not None else None)

    def poll(self) -> MapUpdate:
        self._raise_worker_error()
        with self._out_lock:
            up = self._pending
            self._pending = MapUpdate()
            chunks = self._pending_pids
            self._pending_pids = []
        if chunks:
            up.points, up.colors, up.point_kf = (np.concatenate([c[i] for c in chunks]) for i in range(3))
        return up

    def finish(self) -> MapUpdate:
        self._stop_worker()
        if self.final_global_ba and len(self.map.kfs) > 1:
            with self.map.lock:
                self.run_global_ba(self.cfg.loop.global_ba_iterations)
        with self.map.lock:
            self.mapper.flush_recent()
            self.emit_poses(list(self.map.kfs) + list(self.map.culled))
        if isinstance(self.ba, BundleAdjusterProcess):
            self.ba.close()  # restarted on demand
        return self.poll()

    def trajectory(self) -> dict[int, np.ndarray]:
        out = {}
        with self.map.lock:
            for idx, rec in sorted(self._traj.items()):
                if rec[0] == "abs":
                    out[idx] = rec[2].copy()
                    continue
                base = self.map.kf_pose(rec[1])
                if base is None:
                    continue
                out[idx] = base.copy() if rec[0] == "kf" else rec[2] @ base
        return out

    def lost_frames(self) -> list[int]:
        return sorted(self._lost - set(self._traj))

    def keyframe_frames(self) -> dict[int, int]:
        with self.map.lock:
            return {k: self._kf_frames[k] for k in sorted(self.map.kfs) if k in self._kf_frames}

    def state_dict(self) -> dict:
        """Pickled map + tracker state (stops the mapping thread first)."""
        self._stop_worker()
        with self.map.lock:
            lock = self.map.lock
            self.map.lock = None
            try:
                blob = pickle.dumps({k: getattr(self, k) for k in self._STATE_KEYS}, protocol=pickle.HIGHEST_PROTOCOL)
            finally:
                self.map.lock = lock
        return {"format": "segs.orb.v1", "blob": blob}

    def load_state_dict(self, state: dict) -> None:
        if state.get("format") != "segs.orb.v1":
            raise ConfigError("slam: checkpoint state is not an OrbFrontend state")
        self._stop_worker()
        data = pickle.loads(state["blob"])
        for k, v in data.items():
            setattr(self, k, v)
        self.map.lock = threading.RLock()
        for comp in (self.mapper, self.loop, self.tracker):
            comp.sys = self

    _STATE_KEYS = ("map", "kfdb", "mapper", "loop", "tracker", "_traj", "_lost", "_pending",
                   "_pending_pids", "_kf_frames")

    # ------------------------------------------------------------------ mapping dispatch
    def _dispatch(self, kf: KeyFrame) -> None:
        if not self.threaded:
            self._map_keyframe(kf)
            return
        if self._worker is None:
            self._queue = queue.Queue()
            self._worker = threading.Thread(target=self._work, name="segs-orb-mapping", daemon=True)
            self._worker.start()
        self._queue.put(kf)

    def _map_keyframe(self, kf: KeyFrame) -> None:
        t0 = time.perf_counter()
        self.mapper.process(kf)
        with self.map.lock:
            if kf.kf_id in self.map.kfs:
                self.emit_keyframe(kf)
        t1 = time.perf_counter()
        self.loop.process(kf)
        t2 = time.perf_counter()
        self.times["mapping"].append(t1 - t0)
        self.times["loop"].append(t2 - t1)

    def _work(self) -> None:
        while True:
            kf = self._queue.get()
            try:
                if kf is None:
                    return
                self._busy = True
                self._map_keyframe(kf)
            except BaseException as e:  # surfaced in the caller's thread
                self._worker_error = e
            finally:
                self._busy = False
                self._queue.task_done()

    def _stop_worker(self) -> None:
        if self._worker is not None:
            self._queue.put(None)
            self._worker.join()
            self._worker = None
        self._raise_worker_error()

    def _raise_worker_error(self) -> None:
        if self._worker_error is not None:
            e, self._worker_error = self._worker_error, None
            raise RuntimeError("slam mapping thread failed") from e

    def accepts_keyframes(self) -> bool:
        return not self.threaded or self._queue is None or self._queue.qsize() < 3

    def mapping_idle(self) -> bool:
        return not self.threaded or self._queue is None or (self._queue.empty() and not self._busy)

    # ------------------------------------------------------------------ services for components
    def log(self, msg: str) -> None:
        if self.verbose:
            log.info(msg)
        else:
            log.debug(msg)

    def bow_of(self, desc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.vocab.bow(self.vocab.words(desc))

    def index_keyframe(self, kf: KeyFrame) -> None:
        if kf.kf_id not in self.kfdb.bows:
            self.kfdb.add(kf.kf_id, self.bow_of(kf.kp.desc))

    def reset_map(self) -> None:
        """Drop a rejected (monocular) initial map; keyframe ids keep counting (never reused)."""
        next_id = self.map.next_kf_id
        self.map = Map(self.scales)
        self.map.next_kf_id = next_id
        self.kfdb = KeyFrameDatabase()
        self.mapper.recent = []

    def record_initial_keyframe(self, kf: KeyFrame) -> None:
        """The monocular reference frame becomes keyframe 0 after its frame was reported lost."""
        self._traj[kf.frame_index] = ("kf", kf.kf_id)
        self._kf_frames[kf.kf_id] = kf.frame_index
        self._lost.discard(kf.frame_index)
        self.emit_keyframe(kf)

    def record_waiting_frame(self, frame_index: int, kf_id: int, rel: np.ndarray) -> None:
        """A frame reported lost before the monocular initialization, tracked afterwards against
        the initial map: pose rel [4,4] = w2c relative to keyframe kf_id (trajectory() only)."""
        self._traj[frame_index] = ("rel", kf_id, rel.copy())
        self._lost.discard(frame_index)

    def run_global_ba(self, iterations: int) -> None:
        """Global BA (origin fixed) under the map lock; reports the pose changes as corrections."""
        m = self.map
        old = {k: f.w2c.copy() for k, f in m.kfs.items()}
        self.mapper.global_ba(None, iterations)
        corr = {k: inv_se3(f.w2c) @ old[k] for k, f in m.kfs.items() if k in old}
        for c in m.culled.values():
            a = m.live_ancestor(c.kf_id)
            if a in corr:
                corr[c.kf_id] = corr[a]
        self.emit_corrections(corr)
        self.emit_poses(list(m.kfs) + list(m.culled))
        self.tracker.on_map_corrected()

    # ------------------------------------------------------------------ output buffer
    def emit_keyframe(self, kf: KeyFrame) -> None:
        with self._out_lock:
            if kf.kf_id not in self._pending.new_keyframes:
                self._pending.new_keyframes.append(kf.kf_id)
            self._pending.poses[kf.kf_id] = kf.w2c.copy()

    def emit_poses(self, kf_ids: list[int]) -> None:
        """Refreshed w2c of keyframes; culled ones (still trained by the mapper) are recomposed
        from their parent (ORB-SLAM's Tcp)."""
        with self._out_lock:
            for k in kf_ids:
                if k in self.map.kfs:
                    self._pending.poses[k] = self.map.kfs[k].w2c.copy()
                elif k in self.map.culled:
                    T = self.map.kf_pose(k)
                    if T is not None:
                        self._pending.poses[k] = T

    def emit_points(self, pids: np.ndarray) -> None:
        m = self.map
        pids = np.asarray(pids, np.int64)
        pids = pids[m.valid[pids] & ~m.emitted[pids]]
        if len(pids) == 0:
            return
        m.emitted[pids] = True
        chunk = (m.pos[pids].copy(), m.color[pids].copy(), m.first_kf[pids].copy())
        with self._out_lock:
            self._pending_pids.append(chunk)

    def emit_corrections(self, corr: dict[int, np.ndarray]) -> None:
        """Record corrections; points not yet polled are moved now (an update is self-consistent:
        its points are already in the corrected world, its corrections concern earlier polls)."""
        with self._out_lock:
            self._pending = self._pending.merge(MapUpdate(corrections=corr))
            chunks = []
            for pos, col, kfs in self._pending_pids:
                pos = pos.copy()
                for k in np.unique(kfs).tolist():
                    T = corr.get(int(k))
                    if T is not None:
                        sel = kfs == k
                        pos[sel] = pos[sel] @ T[:3, :3].T + T[:3, 3]
                chunks.append((pos, col, kfs))
            self._pending_pids = chunks

    # ------------------------------------------------------------------ statistics
    def stats(self) -> dict[str, Any]:
        t = {k: np.array(v) for k, v in self.times.items()}
        return {
            "frames": len(self._traj) + len(self.lost_frames()),
            "tracked": len(self._traj),
            "lost": len(self.lost_frames()),
            "keyframes": len(self.map.kfs),
            "culled_keyframes": len(self.map.culled),
            "points": int(self.map.valid[: self.map.n].sum()),
            "loops": len(self.loop.loops),
            "track_ms_median": float(np.median(t["track"]) * 1e3) if len(t["track"]) else float("nan"),
            "mapping_ms_median": float(np.median(t["mapping"]) * 1e3) if len(t["mapping"]) else float("nan"),
            "local_ba_ms_median": float(np.median(self.mapper.ba_times) * 1e3) if self.mapper.ba_times else float("nan"),
        }
