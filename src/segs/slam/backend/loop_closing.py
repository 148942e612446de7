"""Loop closing (ORB-SLAM2's LoopClosing): detection, geometric verification, correction.

Detection: bag-of-words candidates scoring at least the keyframe's worst covisible score, outside
its covisibility, consistent over `consistency` consecutive keyframes. Verification: ORB matches
with the candidate's points, RANSAC over 3D-3D correspondences (Umeyama; SE(3) for stereo / RGB-D,
Sim(3) for monocular), then a guided projection search with the candidate's neighbourhood.
Correction: the keyframe and its covisible neighbours are moved by the loop transform (with their
points), loop points are fused, an essential-graph pose optimisation (gtsam Pose3 / Similarity3
between factors over spanning tree, loop edges and strong covisibility edges) spreads the error, map
points follow their reference keyframe, and a global bundle adjustment follows. Every keyframe's
world-to-world similarity ``c2w_new @ w2c_old`` is reported as a correction.
"""
from __future__ import annotations

from typing import Callable, Protocol

import numpy as np

from segs.slam.geometry import inv_se3, transform, umeyama
from segs.slam.config import LoopConfig
from segs.slam.map.map import KeyFrame, Map
from segs.slam.estimation.matching import TH_LOW, match_frame_to_kf
from segs.slam.estimation.optimize import pose_graph
from segs.slam.outbox import MapOutbox
from segs.slam.sensor import SensorSetup
from segs.slam.map.vocabulary import KeyFrameDatabase, bow_score
from segs.slam.state import StateFields

CHI2_SIM3 = 9.21


def similarity_to_se3(S: np.ndarray) -> np.ndarray:
    """Similarity w2c [[sR, t]] -> rigid w2c [[R, t/s]] (same camera, map rescaled by 1/s)."""
    s = float(np.cbrt(np.linalg.det(S[:3, :3])))
    T = np.eye(4)
    T[:3, :3] = S[:3, :3] / s
    U, _, Vt = np.linalg.svd(T[:3, :3])
    T[:3, :3] = U @ Vt
    T[:3, 3] = S[:3, 3] / s
    return T


class MapRefinement(Protocol):
    """What loop closing asks of local mapping (`LocalMapper`): guided projection search, point
    fusion, global bundle adjustment."""

    def project_match(self, kf: KeyFrame, pids: np.ndarray, w2c: np.ndarray, th: float,
                      fuse: bool) -> tuple[np.ndarray, np.ndarray]: ...
    def fuse_into(self, kf: KeyFrame, pids: np.ndarray, th: float | None = None, S: np.ndarray | None = None) -> int: ...
    def global_ba(self, kf_ids: list[int] | None = None, iterations: int = 10, fix_scale: bool = True) -> None: ...


class LoopCloser(StateFields):
    """Loop closing on `map` (see the module docstring), and the global bundle adjustment.

    cfg: the loop group; setup: the sensor; kfdb: loop candidates; local_mapping: local mapping's search,
    fusion and BA; outbox: receives the corrections and the moved poses; on_map_corrected: called
    after keyframes moved (the tracker recomposes its last pose); seed: RANSAC seed; log: events.
    """

    def __init__(self, cfg: LoopConfig, setup: SensorSetup, map_: Map, kfdb: KeyFrameDatabase,
                 local_mapping: MapRefinement, outbox: MapOutbox, on_map_corrected: Callable[[], None], seed: int,
                 log: Callable[[str], None]):
        self.cfg, self.setup, self.map, self.kfdb, self.local_mapping = cfg, setup, map_, kfdb, local_mapping
        self.outbox, self.on_map_corrected, self.seed, self.log = outbox, on_map_corrected, int(seed), log
        self.groups: list[tuple[set[int], int]] = []
        self.last_loop_kf = -(10 ** 9)
        self.loops: list[tuple[int, int]] = []  # (current kf, loop kf)

    _STATE = ("groups", "last_loop_kf", "loops")


    def run_global_ba(self, iterations: int) -> None:
        """Global BA (origin fixed; call under the map lock); reports the pose changes as corrections."""
        m = self.map
        old = {k: f.w2c.copy() for k, f in m.kfs.items()}
        self.local_mapping.global_ba(None, iterations)
        corr = {k: inv_se3(f.w2c) @ old[k] for k, f in m.kfs.items() if k in old}
        for c in m.culled.values():
            a = m.live_ancestor(c.kf_id)
            if a in corr:
                corr[c.kf_id] = corr[a]
        self.outbox.add_corrections(corr)
        self.outbox.add_poses(m.keyframe_poses(list(m.kfs) + list(m.culled)))
        self.on_map_corrected()

    def process(self, kf: KeyFrame) -> bool:
        """Try to close a loop at keyframe kf; True when a loop was corrected."""
        if not self.cfg.enabled:
            return False
        m = self.map
        with m.lock:
            if kf.kf_id not in m.kfs:
                return False
            cands = self._detect(kf)
            if not cands:
                return False
            kf.protected = True
            found = None
            for c in cands:
                found = self._verify(kf, m.kfs[c]) if c in m.kfs else None
                if found is not None:
                    break
            if found is None:
                kf.protected = False
                return False
            self._correct(kf, *found)
            kf.protected = False
            if self.cfg.global_ba:
                self.run_global_ba(self.cfg.global_ba_iterations)
        return True

    # ------------------------------------------------------------------ detection
    def _detect(self, kf: KeyFrame) -> list[int]:
        m = self.map
        if len(m.kfs) < self.cfg.min_kfs or kf.kf_id - self.last_loop_kf < self.cfg.min_kfs_since_loop:
            return []
        bow = self.kfdb.bows.get(kf.kf_id)
        if bow is None:
            return []
        scores = [bow_score(bow, self.kfdb.bows[n]) for n in kf.conn if n in self.kfdb.bows]
        min_score = min(scores) if scores else 0.0
        exclude = set(kf.conn) | {kf.kf_id} | {k for k in m.kfs if k > kf.kf_id - self.cfg.min_gap_kfs}
        cands = self.kfdb.candidates(bow, exclude, min_score,
                                     {k: f.covisible(10) for k, f in m.kfs.items()}, max_out=10)
        if not cands:
            self.groups = []
            return []
        # ORB-SLAM2's consistency check: each previous group extends at most one new group
        enough, new_groups = [], []
        used = [False] * len(self.groups)
        for c in cands:
            group = {c} | set(m.kfs[c].conn)
            consistent_any = False
            for g, (prev, count) in enumerate(self.groups):
                if not group & prev:
                    continue
                consistent_any = True
                n = count + 1
                if not used[g]:
                    new_groups.append((group, n))
                    used[g] = True
                if n >= self.cfg.consistency and c not in enough:
                    enough.append(c)
            if not consistent_any:
                new_groups.append((group, 0))
        self.groups = new_groups
        return enough

    # ------------------------------------------------------------------ verification
    def _verify(self, kf: KeyFrame, cand: KeyFrame):
        """-> (loop kf, Scw [4,4] corrected similarity w2c of kf, matches {kf kp idx: loop pid}) or None."""
        m, su = self.map, self.setup
        fi, pids = match_frame_to_kf(kf, cand, m.valid, ratio=self.cfg.match_ratio, max_dist=TH_LOW)
        if len(fi) < self.cfg.min_matches:
            return None
        X1, ok1 = self._kf_points(kf, fi)
        X2 = transform(cand.w2c, m.pos[pids])
        fi, pids, X1, X2 = fi[ok1], pids[ok1], X1[ok1], X2[ok1]
        cidx = np.array([m.obs[p].get(cand.kf_id, -1) for p in pids.tolist()], np.int64)
        good = cidx >= 0
        fi, pids, X1, X2, cidx = fi[good], pids[good], X1[good], X2[good], cidx[good]
        if len(fi) < self.cfg.min_inliers:
            return None
        S12, inl = self._ransac(X1, X2, kf.kp.uv[fi], cand.kp.uv[cidx],
                                su.sigma2[kf.kp.octave[fi]], su.sigma2[cand.kp.octave[cidx]])
        if S12 is None or inl.sum() < self.cfg.min_inliers:
            return None
        Scw = S12 @ cand.w2c
        loop_pids = self._loop_points(cand)
        matched = {int(f): int(p) for f, p in zip(fi[inl], pids[inl])}
        free = np.array([p for p in loop_pids.tolist() if p not in set(matched.values())], np.int64)
        if len(free):
            q, k = self.local_mapping.project_match(kf, free, Scw, th=self.cfg.guided_search_th, fuse=False)
            for qq, kk in zip(q.tolist(), k.tolist()):
                matched.setdefault(int(kk), int(free[qq]))
        if len(matched) < self.cfg.min_total:
            return None
        self.log(f"loop: keyframe {kf.kf_id} <-> {cand.kf_id}, {int(inl.sum())} inliers, {len(matched)} matches")
        return cand, Scw, matched

    def _kf_points(self, kf: KeyFrame, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Camera-frame 3D of kf keypoints idx: its map point, else its depth -> ([N,3], ok [N])."""
        m = self.map
        pid = kf.points[idx]
        has = (pid >= 0)
        has[has] = m.valid[pid[has]]
        X = np.zeros((len(idx), 3))
        X[has] = transform(kf.w2c, m.pos[pid[has]])
        d = kf.depth[idx]
        dep = ~has & (d > 0)
        X[dep] = self.setup.backproject(kf.kp.uv[idx[dep]], d[dep])
        return X, has | dep

    def _ransac(self, X1, X2, uv1, uv2, s1, s2):
        """S12 (X1 ~ S12 X2) by RANSAC over minimal sets of 3 -> (S [4,4] or None, inliers [N])."""
        su = self.setup
        rng = np.random.default_rng(self.seed)
        with_scale = su.sensor == "mono"
        K = su.K
        n = len(X1)
        best, best_inl = None, np.zeros(n, bool)

        def inliers(S):
            p1 = transform(S, X2)
            p2 = transform(np.linalg.inv(S), X1)
            ok = (p1[:, 2] > 0) & (p2[:, 2] > 0)
            u1 = K[:2, :2] @ (p1[:, :2] / np.where(ok, p1[:, 2], 1)[:, None]).T
            u2 = K[:2, :2] @ (p2[:, :2] / np.where(ok, p2[:, 2], 1)[:, None]).T
            e1 = ((u1.T + K[:2, 2] - uv1) ** 2).sum(1)
            e2 = ((u2.T + K[:2, 2] - uv2) ** 2).sum(1)
            return ok & (e1 < CHI2_SIM3 * s1) & (e2 < CHI2_SIM3 * s2)

        for _ in range(self.cfg.ransac_iterations):
            s = rng.choice(n, 3, replace=False)
            if np.linalg.matrix_rank(X2[s] - X2[s].mean(0), tol=1e-6) < 2:
                continue
            S = umeyama(X2[s], X1[s], with_scale)
            inl = inliers(S)
            if inl.sum() > best_inl.sum():
                best, best_inl = S, inl
                if inl.sum() > 0.9 * n:
                    break
        if best is None or best_inl.sum() < 3:
            return None, best_inl
        S = umeyama(X2[best_inl], X1[best_inl], with_scale)
        inl = inliers(S)
        return (S, inl) if inl.sum() >= best_inl.sum() * 0.8 else (best, best_inl)

    def _loop_points(self, cand: KeyFrame) -> np.ndarray:
        m = self.map
        ids = [cand.kf_id] + cand.covisible()
        arrs = [m.kf_point_ids(m.kfs[k])[1] for k in ids if k in m.kfs]
        return np.unique(np.concatenate(arrs)) if arrs else np.zeros(0, np.int64)

    # ------------------------------------------------------------------ correction
    def _correct(self, kf: KeyFrame, loop: KeyFrame, Scw: np.ndarray, matched: dict[int, int]) -> None:
        m, su = self.map, self.setup
        mono = su.sensor == "mono"
        old = {k: f.w2c.copy() for k, f in m.kfs.items()}
        connected = [kf.kf_id] + [k for k in kf.covisible() if k in m.kfs]
        Twc = inv_se3(kf.w2c)
        corrected = {k: Scw if k == kf.kf_id else old[k] @ Twc @ Scw for k in connected}
        # move the connected keyframes and the points they see
        moved: dict[int, int] = {}
        for k in connected:
            M = np.linalg.inv(corrected[k]) @ old[k]
            _, pids = m.kf_point_ids(m.kfs[k])
            pids = np.array([p for p in pids.tolist() if p not in moved], np.int64)
            if len(pids):
                m.pos[pids] = transform(M, m.pos[pids])
                moved.update((p, k) for p in pids.tolist())
            m.kfs[k].w2c = similarity_to_se3(corrected[k])
        # fuse the loop's points
        for i, p in matched.items():
            p = m.live(p)
            if p < 0:
                continue
            cur = int(kf.points[i])
            if cur >= 0 and m.valid[cur]:
                m.replace_point(cur, p)
            elif kf.kf_id not in m.obs[p]:
                m.add_obs(p, kf, i)
        loop_pids = self._loop_points(loop)
        before = {k: set(m.kfs[k].conn) for k in connected if k in m.kfs}
        for k in connected:
            if k in m.kfs:
                self.local_mapping.fuse_into(m.kfs[k], loop_pids[m.valid[loop_pids]], th=self.cfg.fuse_th, S=corrected[k])
        new_links: dict[int, set[int]] = {}
        for k in connected:
            if k in m.kfs:
                m.update_connections(m.kfs[k])
                new_links[k] = set(m.kfs[k].conn) - before.get(k, set()) - set(connected)
        # essential graph
        init = {k: corrected.get(k, old.get(k, f.w2c)) for k, f in m.kfs.items()}
        edges = self._essential_edges(old, corrected, new_links)
        fixed = {m.origin_kf, loop.kf_id} & set(m.kfs)
        opt = pose_graph(init, edges, fixed, sim3=mono, iterations=self.cfg.pose_graph_iterations)
        # points follow their reference keyframe
        valid = np.flatnonzero(m.valid[: m.n])
        for p in valid.tolist():
            r = moved.get(p, int(m.ref_kf[p]))
            if r not in opt:
                r = m.live_ancestor(r) if m.live_ancestor(r) in opt else None
                if r is None:
                    continue
            M = np.linalg.inv(opt[r]) @ init[r]
            m.pos[p] = M[:3, :3] @ m.pos[p] + M[:3, 3]
        corrections = {}
        for k, S in opt.items():
            m.kfs[k].w2c = similarity_to_se3(S)
            corrections[k] = np.linalg.inv(S) @ old[k]
        for c in m.culled.values():
            a = m.live_ancestor(c.kf_id)
            if a in corrections:
                corrections[c.kf_id] = corrections[a]
        m.update_geometry(valid)
        kf.loop_edges.add(loop.kf_id)
        loop.loop_edges.add(kf.kf_id)
        m.version += 1
        self.last_loop_kf = kf.kf_id
        self.loops.append((kf.kf_id, loop.kf_id))
        self.groups = []
        self.outbox.add_corrections(corrections)
        self.outbox.add_poses(m.keyframe_poses(list(m.kfs) + list(m.culled)))
        self.on_map_corrected()

    def _essential_edges(self, old, corrected, new_links) -> list[tuple[int, int, np.ndarray]]:
        m = self.map
        edges, seen = [], set()

        def add(i, j, Si, Sj):
            key = (min(i, j), max(i, j))
            if key in seen or i not in m.kfs or j not in m.kfs:
                return
            seen.add(key)
            edges.append((i, j, Si @ np.linalg.inv(Sj)))

        # the new loop links first (corrected poses): they must not be shadowed by the same pairs
        # as covisibility edges with the uncorrected poses
        for k, links in new_links.items():
            for n in sorted(links):
                add(k, n, corrected.get(k, old[k]), corrected.get(n, old[n]))
        for k in sorted(m.kfs):
            f = m.kfs[k]
            if f.parent is not None and f.parent in m.kfs:
                add(f.parent, k, old[f.parent], old[k])
            for le in sorted(f.loop_edges):
                if le in m.kfs:
                    add(le, k, old[le], old[k])
            for n, w in sorted(f.conn.items()):
                if w >= self.cfg.covis_edges and n in m.kfs:
                    add(n, k, old[n], old[k])
        return edges
