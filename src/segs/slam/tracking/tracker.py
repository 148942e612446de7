"""Tracking: per-frame pose from the map (ORB-SLAM's Tracking thread).

track(frame): initialise if needed; else constant-velocity prediction + projection matching of the
last frame's points (fallback: descriptor matching against the reference keyframe), motion-only
pose optimisation, then projection matching into the local map (keyframes sharing points with the
frame and their covisible neighbours) and a second optimisation. When tracking fails, the frame is
lost (no pose) and the following frames try relocalization (bag-of-words candidates, PnP RANSAC).
Frames that waited for a two-view initialization (monocular, or a depth-poor stereo / RGB-D start)
are tracked once it succeeds.
The keyframe decision follows ORB-SLAM3 (max / min frame gap, tracked-points ratio against the
reference keyframe, close-point need for stereo / RGB-D).
"""
from __future__ import annotations

from enum import Enum
from typing import Callable, Protocol

import numpy as np

from segs.slam.config import InitConfig, MatchingConfig, TrackingConfig
from segs.slam.features.frame import SlamFrame
from segs.slam.tracking.frame_poses import FramePoses
from segs.slam.geometry import cam_center, inv_se3, orthonormalize, project, transform
from segs.slam.tracking.initialization import MonoInitializer
from segs.slam.map.map import KeyFrame, Map
from segs.slam.estimation.matching import TH_HIGH, match_frame_to_kf, search_projection
from segs.slam.estimation.optimize import CHI2_MONO, pnp_ransac, refine_pose
from segs.slam.outbox import MapOutbox
from segs.slam.sensor import SensorSetup
from segs.slam.map.vocabulary import KeyFrameDatabase, Vocabulary
from segs.slam.state import StateFields


class TrackingState(str, Enum):
    """Tracker state (ORB-SLAM's eTrackingState); a str Enum, so checkpoints that pickled the
    plain strings "init" / "ok" / "lost" still compare equal after loading."""

    NOT_INITIALIZED = "init"  # no map yet (or a new map segment is to be started)
    OK = "ok"  # the last frame was tracked
    LOST = "lost"  # the last frame was lost; the next ones try relocalization


class LocalMapping(Protocol):
    """What tracking asks of local mapping (`LocalMapper`): new points to watch, the monocular
    initial map's bundle adjustment and registration, forgetting a rejected initial map."""

    def add_recent(self, pids: np.ndarray) -> None: ...
    def register_initial(self, kfs: list[KeyFrame], pids: np.ndarray) -> None: ...
    def global_ba(self, kf_ids: list[int] | None = None, iterations: int = 10, fix_scale: bool = True) -> None: ...
    def clear_recent(self) -> None: ...


class MappingStatus(Protocol):
    """Whether local mapping takes a keyframe now (`KeyFrameQueue`; ORB-SLAM's AcceptKeyFrames)."""

    def accepts_keyframes(self) -> bool: ...
    def idle(self) -> bool: ...


class Tracker(StateFields):
    """Tracks frames against `map` and writes each frame's pose record (`poses`, a FramePoses).

    cfg / init_cfg / match_cfg: the tracking, init and matching groups; setup: the sensor;
    vocab / kfdb: relocalization candidates (and cleared with the map); local_mapping: local mapping's
    services; outbox: receives the monocular initial keyframe; mapping: whether local mapping takes
    keyframes; seed: RANSAC seeds; log: event messages. New keyframes are returned by `track`; the caller hands them to mapping.
    """

    def __init__(self, cfg: TrackingConfig, init_cfg: InitConfig, match_cfg: MatchingConfig, setup: SensorSetup,
                 map_: Map, vocab: Vocabulary, kfdb: KeyFrameDatabase, local_mapping: LocalMapping, outbox: MapOutbox,
                 mapping: MappingStatus, seed: int, log: Callable[[str], None]):
        self.cfg, self.init_cfg, self.match_cfg, self.setup, self.map = cfg, init_cfg, match_cfg, setup, map_
        self.vocab, self.kfdb, self.local_mapping, self.outbox, self.mapping = vocab, kfdb, local_mapping, outbox, mapping
        self.seed, self.log = int(seed), log
        self.poses = FramePoses()
        self.state = TrackingState.NOT_INITIALIZED
        self.last: SlamFrame | None = None
        self.velocity: np.ndarray | None = None
        self.ref_kf: int | None = None
        self.last_kf_frame = -(10 ** 9)
        self.last_reloc_frame = -(10 ** 9)
        self.lost_since: int | None = None
        self.init_waited = 0  # stereo / RGB-D frames that could not start the current map segment
        self.last_good_w2c: np.ndarray | None = None
        self._local_key = None
        self._local_kfs: list[int] = []
        self._local_pids = np.zeros(0, np.int64)
        self._max_inl = 0
        # the disparity sigma of RGB-D residuals in use (pixels), and that of the depth-tolerant retry
        self._ur_sigma = setup.ur_sigma
        retry_k = cfg.rgbd_retry_depth_noise
        self._depth_retry_sigma = setup.bf * retry_k if setup.sensor == "rgbd" and retry_k > 0 else None
        self.depth_retries: list[int] = []  # frames tracked only by that retry
        # monocular: the two-view start; stereo / RGB-D: the depth-poor fallback (init.depth_scale_points)
        two_view = setup.mono or init_cfg.depth_scale_points > 0
        self.mono_init = MonoInitializer(init_cfg, setup.K, setup.sigma2, self.seed) if two_view else None

    _STATE = ("poses", "state", "last", "velocity", "ref_kf", "last_kf_frame", "last_reloc_frame", "lost_since",
              "last_good_w2c", "_local_key", "_local_kfs", "_local_pids", "_max_inl", "mono_init", "depth_retries",
              "init_waited")

    def load_state_dict(self, state: dict) -> None:
        """Decoded state fields; the state string is read as the Enum, the two-view initializer's
        frames ({"ref", "waiting"}) go into this tracker's own initializer."""
        init = state.get("mono_init")
        super().load_state_dict({k: v for k, v in state.items() if k != "mono_init"})
        self.state = TrackingState(self.state)
        if init is not None and self.mono_init is not None:
            self.mono_init.ref, self.mono_init.waiting = init["ref"], list(init["waiting"])

    # ------------------------------------------------------------------ entry point
    def track(self, frame: SlamFrame) -> KeyFrame | None:
        """Sets frame.w2c (None when lost) and records it; returns a new keyframe if one was created."""
        with self.map.lock:
            kf = self._track(frame)
            self.poses.record(frame.index, frame.w2c, kf.kf_id if kf is not None else None, frame.ref_kf,
                              self.map.kf_pose)
        return kf

    def _track(self, frame: SlamFrame) -> KeyFrame | None:
        """One frame under the map lock: initialization, tracking or relocalization."""
        if self.state == TrackingState.NOT_INITIALIZED:
            return self._initialize(frame)
        ok = False
        if self.state == TrackingState.OK:
            if self.last is not None and self.last.index == frame.index - 1:
                ok = self._track_motion(frame) and self._track_local_map(frame)
            if not ok:  # the reference keyframe (descriptors, then PnP RANSAC), then the local map
                frame.points[:] = -1
                frame.outlier[:] = False
                ok = self._track_reference(frame) and self._track_local_map(frame)
        else:
            ok = self._relocalize(frame)
        if not ok and self._depth_retry_sigma is not None:
            ok = self._retry_depth_tolerant(frame)
        if not ok:
            return self._lost(frame)
        if self.state != TrackingState.OK:
            self.lost_since = None
        self.state = TrackingState.OK
        if self.last is not None and self.last.w2c is not None and frame.index - self.last.index == 1:
            self.velocity = orthonormalize(frame.w2c @ inv_se3(self.last.w2c))
        else:
            self.velocity = None
        kf = self._create_keyframe(frame) if self._need_keyframe(frame) else None
        frame.points[frame.outlier] = -1
        frame.outlier[:] = False
        self.last = frame
        self.last_good_w2c = frame.w2c
        if kf is None:
            frame.ref_kf = self.ref_kf
        return kf

    def _retry_depth_tolerant(self, frame: SlamFrame) -> bool:
        """RGB-D: the reference keyframe (or relocalization) once more with the looser depth model
        (cfg.rgbd_retry_depth_noise) for a frame the sensor's model lost; counted in depth_retries."""
        self._ur_sigma = self._depth_retry_sigma
        try:
            frame.points[:] = -1
            frame.outlier[:] = False
            if self.state == TrackingState.OK:
                ok = self._track_reference(frame) and self._track_local_map(frame)
            else:
                ok = self._relocalize(frame)
        finally:
            self._ur_sigma = self.setup.ur_sigma
        if ok:
            self.depth_retries.append(frame.index)
        return ok

    def _lost(self, frame: SlamFrame) -> None:
        frame.w2c = None
        self.velocity = None
        if self.state == TrackingState.OK:
            self.lost_since = frame.index
        self.state = TrackingState.LOST
        n_lost = frame.index - (self.lost_since if self.lost_since is not None else frame.index)
        if self.cfg.restart_after_lost and n_lost >= self.cfg.restart_after_lost and self.setup.sensor != "mono":
            self.log(f"frame {frame.index}: lost for {n_lost} frames, restarting at the last pose")
            self.state = TrackingState.NOT_INITIALIZED
        return None

    # ------------------------------------------------------------------ initialization
    def _reset_map(self) -> None:
        """Drop a rejected (monocular) initial map; keyframe ids keep counting (never reused)."""
        self.map.clear()
        self.kfdb.clear()
        self.local_mapping.clear_recent()

    def _initialize(self, frame: SlamFrame) -> KeyFrame | None:
        if self.setup.sensor == "mono":
            return self._initialize_mono(frame)
        need = min(self.cfg.min_init_points, self.setup.n_features // 3)
        if self.init_waited >= self.cfg.init_wait:  # depth-poor views: start with fewer points
            need = min(need, self.cfg.min_init_points_late)
        if int((frame.depth > 0).sum()) < need:
            self.init_waited += 1
            frame.w2c = None
            if self.mono_init is not None and not self.map.kfs:
                return self._initialize_two_view_depth(frame)
            return None
        self.init_waited = 0
        if self.mono_init is not None:
            self.mono_init.reset()
        w2c = self.last_good_w2c if self.last_good_w2c is not None else np.eye(4)
        frame.w2c = w2c.copy()
        kf = KeyFrame(self.map.new_kf_id(), frame, frame.w2c)
        self.map.add_keyframe(kf)
        idx = np.flatnonzero(frame.depth > 0)
        self._add_depth_points(kf, idx)
        frame.points = kf.points.copy()
        return self._after_init(frame, kf)

    def _initialize_two_view_depth(self, frame: SlamFrame) -> KeyFrame | None:
        """Stereo / RGB-D views with too little depth to start a map (first segment only): the
        monocular two-view start, scaled to metres by the depth its points have (median ratio of
        measured to triangulated depth over at least init.depth_scale_points keypoints). Frames
        are fed from the first waiting one; a start is taken once init_wait frames have waited."""
        res = self.mono_init.try_initialize(frame)
        if res is None:
            return None
        scale = self._depth_scale(self.mono_init.ref, frame, res) if self.init_waited > self.cfg.init_wait else None
        if scale is None:  # not yet: the frame waits with the others for a later partner
            self.mono_init.waiting.append(frame)
            return None
        res.w2c = res.w2c.copy()
        res.w2c[:3, 3] *= scale
        res.points = res.points * scale
        kf = self._start_two_view(frame, res, metric=True)
        if kf is not None:
            self.init_waited = 0
            self.log(f"frame {frame.index}: depth-poor start from two views, scaled by the depth of its points")
        return kf

    def _depth_scale(self, ref: SlamFrame, frame: SlamFrame, res) -> float | None:
        """Metres per unit of a two-view reconstruction (reference at the identity): the median of
        measured / triangulated depth over the matched keypoints with depth in either view."""
        z = np.concatenate([res.points[:, 2], transform(res.w2c, res.points)[:, 2]])
        d = np.concatenate([ref.depth[res.idx_ref], frame.depth[res.idx_cur]])
        ok = (d > 0) & (z > 0)
        ratios = d[ok] / z[ok]
        if len(ratios) < self.init_cfg.depth_scale_points:
            return None
        return float(np.median(ratios))

    def _initialize_mono(self, frame: SlamFrame) -> KeyFrame | None:
        frame.w2c = None
        res = self.mono_init.try_initialize(frame)
        if res is None:
            return None
        return self._start_two_view(frame, res, metric=False)

    def _start_two_view(self, frame: SlamFrame, res, metric: bool) -> KeyFrame | None:
        """The map from a two-view result: two keyframes, their points, BA. Not metric (monocular):
        scaled to a median depth of 1 afterwards; metric (stereo / RGB-D): the result is already in
        metres, BA uses the keypoints' depth and every other keypoint with depth becomes a point."""
        m = self.map
        ref = self.mono_init.ref
        ref.w2c = np.eye(4)
        frame.w2c = res.w2c
        kf0 = KeyFrame(m.new_kf_id(), ref, ref.w2c)
        kf1 = KeyFrame(m.new_kf_id(), frame, frame.w2c)
        m.add_keyframe(kf0)
        m.add_keyframe(kf1)
        pids = m.add_points(res.points, kf0, res.idx_ref)
        for p, i in zip(pids.tolist(), res.idx_cur.tolist()):
            m.add_obs(p, kf1, i)
        m.update_geometry(pids)
        m.update_descriptors(pids)
        m.update_connections(kf0)
        m.update_connections(kf1)
        self.local_mapping.global_ba([kf0.kf_id, kf1.kf_id], iterations=self.init_cfg.ba_iterations, fix_scale=False)
        _, p0 = m.kf_point_ids(kf0)
        depth = transform(kf0.w2c, m.pos[p0])[:, 2]
        _, p1 = m.kf_point_ids(kf1)
        if len(p1) < self.init_cfg.min_triangulated or np.median(depth) <= 0:
            self.log(f"frame {frame.index}: two-view initialization rejected, resetting")
            self._reset_map()
            return None
        if not metric:  # scale: median depth of the first keyframe = 1
            s = 1.0 / float(np.median(depth))
            T1 = kf1.w2c.copy()
            T1[:3, 3] *= s
            kf1.w2c = T1
            m.pos[p0] *= s
        else:
            for kf in (kf0, kf1):  # (local mapping's recent points from _add_depth_points)
                self._add_depth_points(kf, np.flatnonzero((kf.depth > 0) & (kf.points < 0)))
        frame.w2c = kf1.w2c.copy()
        frame.points = kf1.points.copy()
        self.local_mapping.register_initial([kf0, kf1], pids)
        waiting = self.mono_init.waiting
        self.mono_init.reset()
        self.poses.add_keyframe(kf0.frame_index, kf0.kf_id)
        self.outbox.add_keyframe(kf0.kf_id, kf0.w2c)
        ref.w2c, ref.points = kf0.w2c.copy(), kf0.points.copy()
        self._track_waiting(ref, kf0, waiting)
        return self._after_init(frame, kf1)

    def _track_waiting(self, ref: SlamFrame, kf0: KeyFrame, frames: list[SlamFrame]) -> None:
        """Monocular: the frames between the two initial views (reported lost while the reference
        waited) tracked against the new map in order, each from the last one tracked (motion-only
        optimisation, then the local map). Their poses join the trajectory relative to keyframe 0;
        no keyframes are made. Tracker state is set afterwards by _after_init."""
        self.last, self.velocity, self._local_key = ref, None, None
        for f in frames:
            self.ref_kf = kf0.kf_id
            f.points[:] = -1
            f.outlier[:] = False
            if not (self._track_motion(f) and self._track_local_map(f)):
                f.w2c = None
                continue
            f.points[f.outlier] = -1
            f.outlier[:] = False
            self.poses.add_relative(f.index, kf0.kf_id, f.w2c @ inv_se3(kf0.w2c))
            self.last = f

    def _after_init(self, frame: SlamFrame, kf: KeyFrame) -> KeyFrame:
        self.state = TrackingState.OK
        self.lost_since = None
        self.velocity = None
        self.ref_kf = kf.kf_id
        self.last_kf_frame = frame.index
        self.last = frame
        self.last_good_w2c = frame.w2c
        self._local_key = None
        return kf

    def _add_depth_points(self, kf: KeyFrame, idx: np.ndarray) -> np.ndarray:
        """Back-project keypoints idx of kf (with depth) into new map points -> ids."""
        pc = self.setup.backproject(kf.kp.uv[idx], kf.depth[idx])
        pw = transform(inv_se3(kf.w2c), pc)
        pids = self.map.add_points(pw, kf, idx)
        self.local_mapping.add_recent(pids)
        return pids

    # ------------------------------------------------------------------ frame-to-frame
    def _track_motion(self, frame: SlamFrame) -> bool:
        """Constant-velocity prediction + projection matching of the last frame's points. Without a
        velocity (after a relocalization) the last pose is the prediction, with a doubled window."""
        th = self.cfg.window_motion if self.setup.sensor == "mono" else self.cfg.window_motion_stereo
        if self.velocity is None:
            frame.w2c = self.last.w2c.copy()
            th *= self.cfg.window_no_velocity_factor
        else:
            frame.w2c = orthonormalize(self.velocity @ self.last.w2c)
        n = self._search_last(frame, th)
        if n < self.cfg.min_matches_motion:
            frame.points[:] = -1
            n = self._search_last(frame, self.cfg.window_retry_factor * th)
        if n < self.cfg.min_matches_motion:
            frame.points[:] = -1
            return False
        return self._optimize(frame) >= self.cfg.min_pose_inliers

    def _search_last(self, frame: SlamFrame, th: float) -> int:
        m, last = self.map, self.last
        idx = np.flatnonzero(last.points >= 0)
        pids = last.points[idx]
        keep = m.valid[pids]
        idx, pids = idx[keep], pids[keep]
        if len(pids) == 0:
            return 0
        pc = transform(frame.w2c, m.pos[pids])
        uv = project(self.setup.K, pc)
        cam = self.setup.camera
        ok = (pc[:, 2] > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        idx, pids, pc, uv = idx[ok], pids[ok], pc[ok], uv[ok]
        oct_ = last.kp.octave[idx]
        radius = th * self.setup.scales[oct_]
        ur = uv[:, 0] - self.setup.bf / pc[:, 2] if self.setup.sensor != "mono" else None
        q, k = search_projection(frame, uv, m.desc[pids], oct_, radius, oct_ - 1, oct_ + 1, ur,
                                 max_dist=TH_HIGH, ratio=1.0, angle=last.kp.angle[idx])
        frame.points[k] = pids[q]
        return len(q)

    def _track_reference(self, frame: SlamFrame) -> bool:
        """Descriptor matching with the reference keyframe: optimisation from the last pose (ORB-SLAM),
        else PnP RANSAC on looser matches (wide baselines, repetitive texture)."""
        m = self.map
        ref = m.kfs.get(self.ref_kf) if self.ref_kf is not None else None
        if ref is None or self.last is None:
            return False
        frame.points[:] = -1
        cfg = self.cfg
        fi, pids = match_frame_to_kf(frame, ref, m.valid, ratio=cfg.ref_match_ratio, max_dist=TH_HIGH // 2)
        if len(fi) >= cfg.min_matches_ref:
            frame.points[fi] = pids
            frame.w2c = self.last.w2c.copy()
            if self._optimize(frame) >= max(cfg.min_pose_inliers, len(fi) // 2):
                return True
        fi, pids = match_frame_to_kf(frame, ref, m.valid, ratio=cfg.pnp_match_ratio, max_dist=TH_HIGH // 2)
        return len(fi) >= cfg.min_matches_ref and self._pnp(frame, fi, pids) >= cfg.min_pose_inliers

    def _pnp(self, frame: SlamFrame, fi: np.ndarray, pids: np.ndarray) -> int:
        """PnP RANSAC + refinement from the matches frame keypoints fi <-> points pids."""
        frame.points[:] = -1
        frame.outlier[:] = False
        w2c, inl = pnp_ransac(self.map.pos[pids], frame.kp.uv[fi], self.setup.K,
                              reproj=np.sqrt(CHI2_MONO) * self.cfg.pnp_reproj_factor, seed=self.seed + frame.index)
        if w2c is None or inl.sum() < self.cfg.min_pose_inliers:
            return 0
        frame.points[fi[inl]] = pids[inl]
        frame.w2c = w2c
        return self._optimize(frame)

    def _optimize(self, frame: SlamFrame, warm: bool = False) -> int:
        """Motion-only optimisation of frame.w2c on its matches; marks outliers; -> inliers.

        warm: frame.w2c was already optimised (the local-map step after frame-to-frame tracking)."""
        m = self.map
        idx = np.flatnonzero(frame.points >= 0)
        pids = frame.points[idx]
        ur = frame.ur[idx] if self.setup.sensor != "mono" else None
        w2c, inl = refine_pose(frame.w2c, m.pos[pids], frame.kp.uv[idx], ur,
                               1.0 / self.setup.sigma2[frame.kp.octave[idx]], self.setup.K, self.setup.bf,
                               ur_sigma=self._ur_sigma, warm=warm)
        frame.w2c = w2c
        frame.outlier[:] = False
        frame.outlier[idx[~inl]] = True
        return int(inl.sum())

    # ------------------------------------------------------------------ local map
    def _update_local_map(self, frame: SlamFrame) -> None:
        m = self.map
        pids = frame.points[(frame.points >= 0) & ~frame.outlier]
        pids = pids[m.valid[pids]]
        votes = {k: v for k, v in m.count_observers(pids).items() if k in m.kfs}
        if not votes:
            return
        self.ref_kf = max(votes, key=lambda k: (votes[k], k))
        order = sorted(votes, key=lambda k: (-votes[k], k))
        cap = self.cfg.local_kfs
        local = list(order[:cap])
        seen = set(local)
        for k in order:
            if len(local) >= cap:
                break
            kf = m.kfs[k]
            extra = kf.covisible(self.cfg.local_map_covisible) + sorted(kf.children) + ([kf.parent] if kf.parent is not None else [])
            for n in extra:
                if n in m.kfs and n not in seen and len(local) < cap:
                    local.append(n)
                    seen.add(n)
        key = (tuple(sorted(local)), m.version)
        if key != self._local_key:
            allp = np.concatenate([m.kfs[k].points for k in local])
            seen_p = np.zeros(len(m.valid), bool)  # sorted unique ids without a sort
            seen_p[allp[allp >= 0]] = True
            self._local_pids = np.flatnonzero(seen_p & m.valid)
            self._local_key = key
        self._local_kfs = local

    def _track_local_map(self, frame: SlamFrame, th: float | None = None) -> bool:
        m = self.map
        self._update_local_map(frame)
        frame.points[frame.outlier] = -1
        frame.outlier[:] = False
        self._search_local(frame, th if th is not None else self._local_th(frame))
        n = self._optimize(frame, warm=True)
        inl = frame.points[(frame.points >= 0) & ~frame.outlier]
        np.add.at(m.found, inl, 1)
        recent = frame.index - self.last_reloc_frame < self.cfg.reloc_recent_frames
        need = self.cfg.min_inliers_reloc if recent else self.cfg.min_inliers
        return n >= need

    def _local_th(self, frame: SlamFrame) -> float:
        th = self.cfg.local_map_th
        if self.setup.sensor == "rgbd":
            th *= self.cfg.local_map_th_rgbd
        if frame.index - self.last_reloc_frame < 2:
            th *= self.cfg.local_map_th_reloc
        return th

    def _search_local(self, frame: SlamFrame, th: float) -> int:
        m, cam, cfg, mc = self.map, self.setup.camera, self.cfg, self.match_cfg
        pids = self._local_pids
        taken = np.zeros(len(m.valid), bool)  # points the frame already matched
        taken[frame.points[frame.points >= 0]] = True
        pids = pids[m.valid[pids] & ~taken[pids]]
        if len(pids) == 0:
            return 0
        P = m.pos[pids]
        pc = transform(frame.w2c, P)
        uv = project(self.setup.K, pc)
        C = cam_center(frame.w2c)
        PO = P - C
        dist = np.linalg.norm(PO, axis=1)
        cos = (PO * m.normal[pids]).sum(1) / np.maximum(dist, 1e-12)
        ok = (pc[:, 2] > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) \
            & (uv[:, 1] < cam.height) & (dist >= mc.dist_margin_min * m.dmin[pids]) \
            & (dist <= mc.dist_margin_max * m.dmax[pids]) & (cos >= mc.min_view_cos)
        pids, pc, uv, dist, cos = pids[ok], pc[ok], uv[ok], dist[ok], cos[ok]
        m.visible[pids] += 1
        level = m.predict_level(pids, dist)
        radius = th * np.where(cos > cfg.local_map_narrow_cos, cfg.local_map_radius_narrow, cfg.local_map_radius_wide) \
            * self.setup.scales[level]
        ur = uv[:, 0] - self.setup.bf / pc[:, 2] if self.setup.sensor != "mono" else None
        q, k = search_projection(frame, uv, m.desc[pids], level, radius, level - 1, level, ur,
                                 max_dist=TH_HIGH, ratio=self.cfg.local_map_ratio)
        frame.points[k] = pids[q]
        return len(q)

    # ------------------------------------------------------------------ relocalization
    def _relocalize(self, frame: SlamFrame) -> bool:
        m = self.map
        bow = self.vocab.bow_of(frame.kp.desc)
        cands = self.kfdb.candidates(bow, set(), 0.0, {k: kf.covisible(10) for k, kf in m.kfs.items()},
                                     max_out=self.cfg.reloc_candidates)
        # recently lost: the last reference keyframe and its best neighbours come first
        recent = []
        ref = m.kfs.get(self.ref_kf) if self.ref_kf is not None else None
        if ref is not None and self.lost_since is not None and frame.index - self.lost_since <= self.cfg.recent_lost:
            recent = [ref.kf_id] + ref.covisible(self.cfg.recent_lost_covisible)
        for c in recent + [c for c in cands if c not in recent]:
            kf = m.kfs.get(c)
            if kf is None:
                continue
            frame.points[:] = -1
            fi, pids = match_frame_to_kf(frame, kf, m.valid, ratio=self.cfg.pnp_match_ratio, max_dist=TH_HIGH // 2)
            if len(fi) < self.cfg.reloc_min_matches:
                continue
            if self._pnp(frame, fi, pids) < self.cfg.min_pose_inliers:
                continue
            frame.points[frame.outlier] = -1
            frame.outlier[:] = False
            self.last_reloc_frame = frame.index
            if self._track_local_map(frame, th=self.cfg.local_map_th * self.cfg.local_map_th_reloc):
                self.log(f"frame {frame.index}: relocalized against keyframe {c}")
                return True
        frame.points[:] = -1
        frame.w2c = None
        return False

    def on_map_corrected(self) -> None:
        """Keyframes moved (loop, global BA): recompose the last frame's pose from its keyframe."""
        self._local_key = None
        if self.last is None or self.last.w2c is None:
            return
        w2c = self.poses.w2c(self.last.index, self.map.kf_pose)
        if w2c is not None:
            self.last.w2c = w2c
            self.last_good_w2c = self.last.w2c

    # ------------------------------------------------------------------ keyframes
    def _need_keyframe(self, frame: SlamFrame) -> bool:
        m, cfg, su = self.map, self.cfg, self.setup
        if not self.mapping.accepts_keyframes() and frame.index - self.last_kf_frame < cfg.kf_max_gap:
            return False
        if frame.index == self.last_reloc_frame and len(m.kfs) > 1:  # not the relocalized frame itself
            return False
        ref = m.kfs.get(self.ref_kf) if self.ref_kf is not None else None
        if ref is None:
            return True
        min_obs = 3 if len(m.kfs) > 2 else 2
        _, rp = m.kf_point_ids(ref)
        n_ref = int((m.n_obs[rp] >= min_obs).sum())
        tracked = (frame.points >= 0) & ~frame.outlier
        n_inl = int(tracked.sum())
        need_close = False
        if su.sensor != "mono":
            close = (frame.depth > 0) & (frame.depth < su.th_depth)
            n_tc = int((close & tracked).sum())
            n_nc = int((close & ~tracked).sum())
            need_close = n_tc < cfg.kf_close_tracked and n_nc > cfg.kf_close_untracked
        ratio = cfg.kf_ref_ratio_mono if su.sensor == "mono" else cfg.kf_ref_ratio
        gap = frame.index - self.last_kf_frame
        c1a = gap >= cfg.kf_max_gap
        min_gap = cfg.kf_min_gap_mono if su.sensor == "mono" else cfg.kf_min_gap
        c1b = self.mapping.idle() and (gap >= min_gap or (su.sensor == "mono" and self._view_changed(frame)))
        c1c = su.sensor != "mono" and (n_inl < cfg.kf_ref_ratio_weak * n_ref or need_close)
        # coverage (ours): the tracked points fell below a share of the best count since the last
        # keyframe; like c1c a need (tracking is about to fail), so it ignores kf_min_gap
        self._max_inl = max(self._max_inl, n_inl)
        low_cover = n_inl < cfg.kf_track_ratio * self._max_inl
        c2 = (n_inl < n_ref * ratio or need_close or low_cover) and n_inl > cfg.kf_min_tracked
        # monocular weak tracking (ORB-SLAM3's c4, there for inertial monocular): fewer than
        # kf_weak_mono tracked points; forward motion leaves the mapped area within frames and
        # keyframes are the only source of new points
        c4 = su.sensor == "mono" and cfg.kf_min_tracked < n_inl < cfg.kf_weak_mono
        return (c2 and (c1a or c1b or c1c or low_cover)) or c4

    def _view_changed(self, frame: SlamFrame) -> bool:
        """Monocular: the camera turned, or moved across the angle its baseline subtends at the
        median depth of the newest keyframe's points, by kf_view_change_deg_mono or more since that
        keyframe. Pacing (kf_min_gap_mono) then no longer holds a keyframe back: it is meant for a
        view that barely changes, as at 30 Hz on a hand-held camera (0: pacing always holds)."""
        deg, m = self.cfg.kf_view_change_deg_mono, self.map
        if deg <= 0 or not m.kfs:
            return False
        kf = m.kfs[max(m.kfs)]
        R = frame.w2c[:3, :3] @ kf.w2c[:3, :3].T
        if np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))) >= deg:
            return True
        _, pids = m.kf_point_ids(kf)
        depth = np.median(transform(kf.w2c, m.pos[pids])[:, 2]) if len(pids) else 0.0
        base = np.linalg.norm(cam_center(frame.w2c) - kf.center)
        return depth > 0 and np.degrees(np.arctan2(base, depth)) >= deg

    def _create_keyframe(self, frame: SlamFrame) -> KeyFrame:
        m = self.map
        frame.points[frame.outlier] = -1
        frame.outlier[:] = False
        kf = KeyFrame(m.new_kf_id(), frame, frame.w2c)
        m.add_keyframe(kf)
        if self.setup.sensor != "mono":
            free = np.flatnonzero((frame.depth > 0) & (kf.points < 0))
            if self.cfg.rgbd_new_points != "all":
                order = free[np.argsort(frame.depth[free], kind="stable")]
                close = frame.depth[order] < self.setup.th_depth
                close[: min(self.cfg.kf_min_new_points, len(close))] = True
                free = np.sort(order[close])
            self._add_depth_points(kf, free)
            frame.points = kf.points.copy()
        self.ref_kf = kf.kf_id
        self.last_kf_frame = frame.index
        self._max_inl = 0
        return kf
