"""Local mapping (ORB-SLAM's LocalMapping thread) for one new keyframe at a time.

process(kf): bag of words + observations of the tracked points + covisibility; culling of recent
map points; new points by triangulation with the best covisible keyframes (epipolar-guided ORB
matching, parallax / reprojection / scale checks; stereo and RGB-D use the keypoint depth when the
rays are too parallel); fusion of duplicates with the neighbours; local bundle adjustment (gtsam)
over the keyframe and its best covisible ones, the others that see those points fixed; redundant
keyframe culling. Points become "mature" (and reach the mapper) once they survive the culling.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from segs.slam.geometry import cam_center, fundamental, inv_se3, project, transform, triangulate
from segs.slam.config import LocalMappingConfig, MatchingConfig
from segs.slam.map.map import KeyFrame, Map
from segs.slam.native import kernels
from segs.slam.estimation.matching import TH_LOW, match_for_triangulation, nearest_two_in_radius, unique_targets
from segs.slam.estimation.optimize import CONVERGED_GAIN, BundleAdjuster, Observations, PointSet, reproj_chi2
from segs.slam.outbox import MapOutbox
from segs.slam.sensor import SensorSetup
from segs.slam.map.vocabulary import KeyFrameDatabase, Vocabulary
from segs.slam.state import StateFields


class LocalMapper(StateFields):
    """Local mapping of one keyframe at a time on `map` (see the module docstring).

    cfg / match_cfg: the local_mapping and matching groups; setup: the sensor; vocab / kfdb: bag of words of each new keyframe
    into the keyframe database; ba: the bundle adjuster (`optimize.BundleAdjuster` or its child
    process twin, `run_two_pass`); outbox: receives the mature points and the poses BA touched;
    log: event messages.
    """

    def __init__(self, cfg: LocalMappingConfig, match_cfg: MatchingConfig, setup: SensorSetup, map_: Map,
                 vocab: Vocabulary, kfdb: KeyFrameDatabase, ba: BundleAdjuster, outbox: MapOutbox,
                 log: Callable[[str], None]):
        self.cfg, self.match_cfg, self.setup, self.map, self.vocab, self.kfdb = cfg, match_cfg, setup, map_, vocab, kfdb
        self.ba, self.outbox, self.log = ba, outbox, log
        self.recent: list[int] = []  # young points (ids), culled or mature after a few keyframes
        self.ba_times: list[float] = []  # seconds per bundle adjustment
        parallax = cfg.min_parallax_deg_mono if setup.sensor == "mono" else cfg.min_parallax_deg
        self.cos_parallax = float(np.cos(np.radians(parallax)))

    _STATE = ("recent", "ba_times")


    def add_recent(self, pids: np.ndarray) -> None:
        self.recent.extend(int(p) for p in pids)

    def clear_recent(self) -> None:
        """The map was cleared (a rejected monocular initial map)."""
        self.recent = []

    def register_initial(self, kfs: list[KeyFrame], pids: np.ndarray) -> None:
        """Monocular initial map: keyframes already connected; words + database only."""
        for kf in kfs:
            self._index_keyframe(kf)
        self.add_recent(pids)

    def _index_keyframe(self, kf: KeyFrame) -> None:
        """The keyframe's bag of words into the keyframe database (once)."""
        if len(kf.words) != len(kf.kp):
            kf.words = self.vocab.words(kf.kp.desc)
        if kf.kf_id not in self.kfdb.bows:
            self.kfdb.add(kf.kf_id, self.vocab.bow(kf.words))

    def _emit_points(self, pids: np.ndarray) -> None:
        """Points pids reach the mapper (those valid and not handed out before)."""
        chunk = self.map.take_new_points(pids)
        if chunk is not None:
            self.outbox.add_points(*chunk)

    # ------------------------------------------------------------------ main step
    def process(self, kf: KeyFrame) -> None:
        m = self.map
        with m.lock:
            if kf.bad:
                return
            self._process_new(kf)
            if self.cfg.cull_points:
                self._cull_recent(kf)
            self._triangulate(kf)
            self._fuse(kf)
        self.local_ba(kf)
        with m.lock:
            if self.cfg.cull_keyframes:
                self._cull_keyframes(kf)

    def _process_new(self, kf: KeyFrame) -> None:
        m = self.map
        idx = np.flatnonzero(kf.points >= 0)
        live = m.live_ids(kf.points[idx])
        kf.points[idx[live < 0]] = -1
        m.observe(kf, idx[live >= 0], live[live >= 0])
        _, pids = m.kf_point_ids(kf)
        m.update_geometry(pids)
        m.update_descriptors(pids)
        m.update_connections(kf)
        self._index_keyframe(kf)

    def _cull_recent(self, kf: KeyFrame) -> None:
        m = self.map
        cfg = self.cfg
        th_obs = cfg.recent_min_obs_mono if self.setup.sensor == "mono" else cfg.recent_min_obs
        keep, mature = [], []
        for p in self.recent:
            if not m.valid[p]:
                continue
            age = kf.kf_id - m.first_kf[p]
            if m.found[p] / max(m.visible[p], 1) < self.cfg.min_found_ratio:
                m.set_point_bad(p)
            elif age >= cfg.recent_cull_age and m.n_obs[p] <= th_obs:
                m.set_point_bad(p)
            elif age >= cfg.recent_mature_age:
                mature.append(p)
            else:
                keep.append(p)
        self.recent = keep
        self._emit_points(np.array(mature, np.int64))

    def flush_recent(self) -> None:
        """End of sequence: every surviving recent point is emitted."""
        m = self.map
        self._emit_points(np.array([p for p in self.recent if m.valid[p]], np.int64))
        self.recent = []

    # ------------------------------------------------------------------ triangulation
    def _triangulate(self, kf: KeyFrame) -> None:
        m, su = self.map, self.setup
        mono = su.sensor == "mono"
        nn = self.cfg.triangulate_neighbors * (2 if mono else 1)
        K, bf = su.K, su.bf
        base_stereo = bf / K[0, 0]
        ratio_factor = self.cfg.scale_consistency * su.scale_factor
        P1 = K @ kf.w2c[:3]
        C1 = kf.center
        partners = []
        for n in kf.covisible(nn):
            kf2 = m.kfs.get(n)
            if kf2 is None:
                continue
            baseline = np.linalg.norm(kf2.center - C1)
            if mono:
                _, p2 = m.kf_point_ids(kf2)
                if len(p2) == 0:
                    continue
                ratio = baseline / max(float(np.median(transform(kf2.w2c, m.pos[p2])[:, 2])), 1e-9)
                if ratio < self.cfg.min_baseline_ratio:
                    continue
                partners.append((-ratio, n))
            elif baseline >= base_stereo:
                partners.append((0.0, n))
        # monocular: widest baselines first, so that each keypoint is triangulated with the best
        # partner (adjacent keyframes have the most shared points but the least parallax). The new
        # points' geometry and descriptors are computed once at the end: nothing in the loop reads them
        new = []
        for _, n in sorted(partners, key=lambda t: t[0]) if mono else partners:
            kf2 = m.kfs[n]
            F = fundamental(kf.w2c, kf2.w2c, K)
            i1, i2 = match_for_triangulation(kf, kf2, F, su.sigma2, ratio=self.cfg.triangulate_ratio,
                                             nodes=self._nodes(kf, kf2))
            if len(i1) == 0:
                continue
            X, ok = self._triangulate_pairs(kf, kf2, i1, i2, P1, base_stereo, ratio_factor)
            if ok.any():
                pids = m.add_points(X[ok], kf, i1[ok], geometry=False)
                for p, j in zip(pids.tolist(), i2[ok].tolist()):
                    m.add_obs(p, kf2, j)
                new.append(pids)
                self.add_recent(pids)
        if new:
            pids = np.concatenate(new)
            m.update_geometry(pids)
            m.update_descriptors(pids)

    def _nodes(self, kf1: KeyFrame, kf2: KeyFrame) -> tuple[np.ndarray, np.ndarray] | None:
        """Vocabulary-tree node per keypoint of both keyframes at triangulate_node_level (None:
        level 0, or a keyframe without words, e.g. from an older checkpoint)."""
        level = self.cfg.triangulate_node_level
        if level <= 0 or len(kf1.words) != len(kf1.kp) or len(kf2.words) != len(kf2.kp):
            return None
        return self.vocab.nodes(kf1.words, level), self.vocab.nodes(kf2.words, level)

    def _triangulate_pairs(self, kf1, kf2, i1, i2, P1, base_stereo, ratio_factor):
        su = self.setup
        K, Ki = su.K, np.linalg.inv(su.K)
        x1, x2 = kf1.kp.uv[i1], kf2.kp.uv[i2]
        R1w, R2w = kf1.w2c[:3, :3], kf2.w2c[:3, :3]
        r1 = (np.c_[x1, np.ones(len(x1))] @ Ki.T) @ R1w  # world rays (unnormalised)
        r2 = (np.c_[x2, np.ones(len(x2))] @ Ki.T) @ R2w
        cos_rays = (r1 * r2).sum(1) / (np.linalg.norm(r1, axis=1) * np.linalg.norm(r2, axis=1))
        d1, d2 = kf1.depth[i1], kf2.depth[i2]
        s1, s2 = d1 > 0, d2 > 0
        cos_st1 = np.where(s1, np.cos(2 * np.arctan2(base_stereo / 2, np.where(s1, d1, 1))), 2.0)
        cos_st2 = np.where(s2, np.cos(2 * np.arctan2(base_stereo / 2, np.where(s2, d2, 1))), 2.0)
        cos_st = np.minimum(cos_st1, cos_st2)
        tri = (cos_rays > 0) & (cos_rays < cos_st) & ((s1 | s2) | (cos_rays < self.cos_parallax))
        X = triangulate(P1, K @ kf2.w2c[:3], x1, x2)
        use1 = ~tri & s1 & (cos_st1 <= cos_st2)
        use2 = ~tri & s2 & ~use1
        X[use1] = self._unproject(kf1, i1[use1])
        X[use2] = self._unproject(kf2, i2[use2])
        ok = (tri | use1 | use2) & np.isfinite(X).all(1)
        for kf, idx in ((kf1, i1), (kf2, i2)):
            chi2, th, z = reproj_chi2(kf.w2c, X, kf.kp.uv[idx], kf.ur[idx], 1.0 / su.sigma2[kf.kp.octave[idx]],
                                      K, su.bf, su.ur_sigma)
            ok &= (z > 0) & (chi2 < th)
        dist1 = np.linalg.norm(X - kf1.center, axis=1)
        dist2 = np.linalg.norm(X - kf2.center, axis=1)
        ratio_dist = dist2 / np.maximum(dist1, 1e-12)
        ratio_oct = su.scales[kf1.kp.octave[i1]] / su.scales[kf2.kp.octave[i2]]
        ok &= (dist1 > 0) & (dist2 > 0) & (ratio_dist * ratio_factor >= ratio_oct) & (ratio_dist <= ratio_oct * ratio_factor)
        return X, ok

    def _unproject(self, kf: KeyFrame, idx: np.ndarray) -> np.ndarray:
        """World points [N,3] of keypoints idx [N] of kf at their depth."""
        return transform(inv_se3(kf.w2c), self.setup.backproject(kf.kp.uv[idx], kf.depth[idx]))

    # ------------------------------------------------------------------ fusion
    def _fuse(self, kf: KeyFrame) -> None:
        m = self.map
        nn = self.cfg.fuse_neighbors * (2 if self.setup.sensor == "mono" else 1)
        targets = []
        for n in kf.covisible(nn):
            if n in m.kfs and n not in targets:
                targets.append(n)
                for n2 in m.kfs[n].covisible(self.cfg.fuse_second_neighbors):
                    if n2 != kf.kf_id and n2 in m.kfs and n2 not in targets:
                        targets.append(n2)
        _, own = m.kf_point_ids(kf)
        for t in targets:
            self.fuse_into(m.kfs[t], own)
        cand = [m.kf_point_ids(m.kfs[t])[1] for t in targets]
        if cand:
            pids = np.unique(np.concatenate(cand))
            self.fuse_into(kf, pids)
        _, own = m.kf_point_ids(kf)
        m.update_geometry(own)
        m.update_descriptors(own)
        m.update_connections(kf)

    def fuse_into(self, kf: KeyFrame, pids: np.ndarray, th: float | None = None, S: np.ndarray | None = None) -> int:
        """Project points pids into kf and merge with what its keypoints hold (ORB-SLAM Fuse).

        pids [M]: point ids; th: projection radius x level scale (None: mapping.fuse_th); S: optional
        similarity w2c [4,4] used for the projection instead of kf.w2c (loop fusion).
        Returns the number of fused / added observations.
        """
        m = self.map
        pids = pids[m.valid[pids]]
        pids = pids[m.unobserved_by(pids, kf.kf_id)]
        if len(pids) == 0:
            return 0
        w2c = S if S is not None else kf.w2c
        q, k = self.project_match(kf, pids, w2c, self.cfg.fuse_th if th is None else th, fuse=True)
        n, merged = 0, []
        for p, i in zip(pids[q].tolist(), k.tolist()):
            if not m.valid[p] or kf.kf_id in m.obs[p]:
                continue
            cur = int(kf.points[i])
            if cur >= 0 and m.valid[cur]:
                keep, drop = (cur, p) if m.n_obs[cur] > m.n_obs[p] else (p, cur)
                m.replace_point(drop, keep, update_descriptor=False)
                merged.append(keep)
                if keep == p and kf.kf_id not in m.obs[p]:
                    m.add_obs(p, kf, i)
            else:
                m.add_obs(p, kf, i)
            n += 1
        alive = np.unique(m.live_ids(np.asarray(merged, np.int64)))
        if len(alive) and alive[-1] >= 0:
            m.update_descriptors(alive[alive >= 0])
        return n

    def project_match(self, kf: KeyFrame, pids: np.ndarray, w2c: np.ndarray, th: float,
                      fuse: bool) -> tuple[np.ndarray, np.ndarray]:
        """Vectorized projection search of points into a keyframe (chi2-gated when fuse)."""
        m, su, cam, mc = self.map, self.setup, self.setup.camera, self.match_cfg
        s = float(np.cbrt(np.linalg.det(w2c[:3, :3])))
        P = m.pos[pids]
        pc = transform(w2c, P)
        uv = project(su.K, pc)
        C = -np.linalg.inv(w2c[:3, :3]) @ w2c[:3, 3]
        PO = P - C
        dist = np.linalg.norm(PO, axis=1)
        cos = (PO * m.normal[pids]).sum(1) / np.maximum(dist, 1e-12)
        ok = (pc[:, 2] > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height) \
            & (dist >= mc.dist_margin_min * m.dmin[pids]) & (dist <= mc.dist_margin_max * m.dmax[pids]) \
            & (cos >= mc.min_view_cos)
        sel = np.flatnonzero(ok)
        level = m.predict_level(pids[sel], dist[sel])
        radius = th * su.scales[level]
        gate = (pc[sel, 2] / s, su.sigma2, su.ur_sigma, su.bf) if fuse else None
        q, k, d1, _ = nearest_two_in_radius(kf, np.ascontiguousarray(uv[sel]), m.desc[pids[sel]], radius, level - 1,
                                            level, None, False, gate)
        keep = d1 <= TH_LOW
        q, k, d1 = q[keep], k[keep], d1[keep]
        keep = unique_targets(q, k, d1)
        return sel[q[keep]], k[keep]

    # ------------------------------------------------------------------ bundle adjustment
    def local_ba(self, kf: KeyFrame) -> None:
        m = self.map
        with m.lock:
            if kf.kf_id not in m.kfs:
                return
            window = [kf.kf_id] + [k for k in kf.covisible(self.cfg.ba_window - 1) if k in m.kfs]
        its = self.cfg.ba_iterations_rgbd if self.setup.sensor == "rgbd" else self.cfg.ba_iterations
        self.run_ba(window, self.cfg.ba_fixed_max, its, min_gain=self.cfg.ba_min_gain)

    def global_ba(self, kf_ids: list[int] | None = None, iterations: int = 10, fix_scale: bool = True) -> None:
        """BA of kf_ids (default: all keyframes) with the origin fixed; fix_scale: see run_ba."""
        m = self.map
        with m.lock:
            window = sorted(m.kfs) if kf_ids is None else list(kf_ids)
        self.run_ba(window, 0, (iterations, iterations // 2), global_=True, fix_scale=fix_scale)

    def run_ba(self, window: list[int], fixed_max: int, iterations, global_: bool = False,
               fix_scale: bool = True, min_gain: float = CONVERGED_GAIN) -> None:
        """Bundle adjustment of window keyframes + their points; observers outside stay fixed.

        fix_scale (monocular): with a single fixed keyframe the scale is a free gauge and LM
        wanders along it (the whole young map shrank or grew by 2-5x in one BA); the result is
        then scaled back about the fixed camera (an exact gauge move: no reprojection error
        changes) to the points' median distance from it before the BA. False only for the
        two-view initialization, whose scale is normalised afterwards."""
        import time

        t0 = time.perf_counter()
        m, su = self.map, self.setup
        with m.lock:
            problem = self._build_problem(window, fixed_max)
        if problem is None:
            return
        poses, fixed, points, obs, rigid = problem
        new_poses, new_points, bad = self.ba.run_two_pass(poses, fixed, points, obs, iterations, min_gain)
        if fix_scale and su.sensor == "mono" and len(fixed) == 1:
            self._keep_gauge_scale(poses[next(iter(fixed))], points, new_poses, new_points, fixed)
        with m.lock:
            self._move_rigid(rigid, poses, new_poses)
            self._write_back(window, new_poses, fixed, new_points, obs, bad)
        self.ba_times.append(time.perf_counter() - t0)

    @staticmethod
    def _keep_gauge_scale(fixed_w2c: np.ndarray, points: PointSet, new_poses: dict, new_points: PointSet,
                          fixed: set) -> None:
        """Scale new_poses / new_points (in place) about the fixed camera centre so that the
        points' median distance from it is what it was before the BA."""
        if not len(points.pid):
            return
        c = cam_center(fixed_w2c)
        before = np.median(np.linalg.norm(points.xyz - c, axis=1))
        after = np.median(np.linalg.norm(new_points.xyz - c, axis=1))
        if not (before > 0 and after > 0):
            return
        s = before / after
        new_points.xyz[:] = c + s * (new_points.xyz - c)
        for k, T in new_poses.items():
            if k not in fixed:
                T = T.copy()
                T[:3, 3] = -T[:3, :3] @ (c + s * (cam_center(T) - c))
                new_poses[k] = T

    def _move_rigid(self, rigid, old_poses, new_poses) -> None:
        """Points left out of BA follow their only keyframe: p <- T_new^-1 T_old p."""
        m = self.map
        kfs, pids = rigid
        for k in np.unique(kfs).tolist():
            sel = pids[(kfs == k) & m.valid[pids]]
            if len(sel) and k in m.kfs:
                M = inv_se3(new_poses[k]) @ old_poses[k]
                m.pos[sel] = m.pos[sel] @ M[:3, :3].T + M[:3, 3]

    def _build_problem(self, window: list[int], fixed_max: int):
        m, mono = self.map, self.setup.sensor == "mono"
        window = [k for k in window if k in m.kfs]
        if not window:
            return None
        local = np.unique(np.concatenate([m.kf_point_ids(m.kfs[k])[1] for k in window]))
        if len(local) == 0:
            return None
        wset = set(window)
        fixed_ids = []
        if fixed_max:  # the outside keyframes seeing most local points (ties: lower id first)
            kfid = m.observers(local)[1]
            out, counts = np.unique(kfid[~np.isin(kfid, window)], return_counts=True)
            fixed_ids = out[np.lexsort((out, -counts))][:fixed_max].tolist()
        fixed = set(fixed_ids)
        if m.origin_kf in wset:
            fixed.add(m.origin_kf)
        if not fixed:
            fixed.add(min(window))
        kfs = window + fixed_ids
        lset = np.zeros(m.n, bool)
        lset[local] = True
        ks, ps, ids = [], [], []
        for k in kfs:
            idx, pids = m.kf_point_ids(m.kfs[k])
            sel = lset[pids]
            ks.append(np.full(int(sel.sum()), k))
            ps.append(pids[sel])
            ids.append(idx[sel])
        kk, pp = np.concatenate(ks), np.concatenate(ps)
        ur = np.concatenate([m.kfs[k].ur[i] for k, i in zip(kfs, ids)]) if not mono else np.full(len(kk), -1.0)
        uv = np.concatenate([m.kfs[k].kp.uv[i] for k, i in zip(kfs, ids)])
        octv = np.concatenate([m.kfs[k].kp.octave[i] for k, i in zip(kfs, ids)])
        # a point needs two views (or one with depth) to be determined; a point seen only by one
        # keyframe with depth adds nothing to the poses (3 equations, 3 unknowns): it is left out
        # and moved rigidly with its keyframe afterwards ("rigid"), which halves RGB-D problems
        n_in = np.bincount(pp, minlength=m.n)[pp]
        n_view = n_in + np.bincount(pp, weights=(ur >= 0), minlength=m.n)[pp]
        rigid = (n_in == 1) & (ur >= 0) & (m.n_obs[pp] == 2)
        keep = (n_view >= 2) & ~rigid
        obs = Observations(kk[keep], pp[keep], uv[keep], ur[keep], octv[keep])
        ids = np.unique(obs.pid)
        pts = PointSet(ids, m.pos[ids])
        poses = {k: m.kfs[k].w2c.copy() for k in kfs}
        return poses, fixed, pts, obs, (kk[rigid], pp[rigid])

    def _write_back(self, window, new_poses, fixed, new_points, obs, bad) -> None:
        m = self.map
        min_obs = 2 if self.setup.sensor == "mono" else 1
        for k, p in zip(obs.kf[bad].tolist(), obs.pid[bad].tolist()):
            if m.valid[p]:
                m.erase_obs(p, k, min_obs)
        touched = []
        for k in window:
            if k in m.kfs and k not in fixed:
                m.kfs[k].w2c = new_poses[k]
                touched.append(k)
        ok = m.valid[new_points.pid]
        pids = new_points.pid[ok]
        m.pos[pids] = new_points.xyz[ok]
        m.update_geometry(pids)
        self.outbox.add_poses(self.map.keyframe_poses(touched))

    # ------------------------------------------------------------------ keyframe culling
    def _cull_keyframes(self, kf: KeyFrame) -> None:
        """ORB-SLAM's redundancy test: a covisible keyframe is culled when more than `redundancy`
        of its (close) points are seen by at least 3 other keyframes at the same or a finer scale."""
        m, su = self.map, self.setup
        th_obs = self.cfg.redundant_observers
        octaves = None  # keyframe id -> its keypoints' octaves, built when first needed
        for n in kf.covisible(self.cfg.cull_window):
            k = m.kfs.get(n)
            if k is None or n == m.origin_kf or k.protected or n == kf.kf_id:
                continue
            idx, pids = m.kf_point_ids(k)
            if su.sensor != "mono":
                close = (k.depth[idx] > 0) & (k.depth[idx] < su.th_depth)
                idx, pids = idx[close], pids[close]
            many = m.n_obs[pids] > th_obs  # points seen often enough to be redundant at all
            if len(pids) == 0 or many.sum() <= self.cfg.redundancy * len(pids):
                continue
            if octaves is None:
                octaves = {kid: kk.kp.octave for kid, kk in m.kfs.items()}
            redundant = redundant_points(m.obs, pids[many], k.kp.octave[idx[many]] + 1, n, octaves, th_obs)
            if redundant > self.cfg.redundancy * len(pids):
                m.set_kf_bad(k)
                octaves.pop(n, None)
                self.kfdb.erase(n)
                self.log(f"culled keyframe {n}")


def redundant_points(obs: list[dict[int, int]], pids: np.ndarray, level: np.ndarray, exclude: int,
                     octaves: dict[int, np.ndarray], th_obs: int, native: bool = True) -> int:
    """How many of the points pids [P] are seen by at least th_obs keyframes other than `exclude`
    (among the keys of octaves, the map's keyframes -> their keypoints' octaves) at an octave
    <= level [P] (ORB-SLAM's KeyFrameCulling count). native: the C++ loop where it is built."""
    ext = kernels() if native else None
    if ext is not None:
        return int(ext.redundant_points(obs, pids, level, exclude, octaves, th_obs))
    redundant = 0
    for p, lvl in zip(pids.tolist(), level.tolist()):
        cnt = 0
        for k2, j in obs[p].items():
            if k2 != exclude and k2 in octaves and octaves[k2][j] <= lvl:
                cnt += 1
                if cnt >= th_obs:
                    redundant += 1
                    break
    return redundant
