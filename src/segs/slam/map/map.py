"""The SLAM map: keyframes with a covisibility graph and spanning tree, and map points.

Map points live in growable structure-of-arrays (positions, descriptors, viewing normals, scale
ranges, counters) so that tracking can project and match thousands of them without Python loops;
each point's observations are a small dict ``kf_id -> keypoint index`` (mapping-side work).
Keyframe ids are never reused; a culled keyframe is remembered by its pose relative to its parent
so that the frames tracked against it keep a pose.
"""
from __future__ import annotations

import threading
from dataclasses import dataclass
from itertools import chain

import numpy as np

from segs.slam.features.extractor import Keypoints
from segs.slam.features.frame import KeypointGrid, SlamFrame
from segs.slam.geometry import cam_center, inv_se3
from segs.slam.native import kernels


class KeyFrame:
    """A keyframe: the frame's features, its w2c pose [4,4], map point per keypoint, graph links."""

    def __init__(self, kf_id: int, frame: SlamFrame, w2c: np.ndarray):
        self.kf_id = kf_id
        self.frame_index = frame.index
        self.timestamp = frame.timestamp
        self.kp: Keypoints = frame.kp
        self.depth = frame.depth
        self.ur = frame.ur
        self.colors = frame.colors
        self.grid: KeypointGrid = frame.grid
        self.points = np.where(frame.outlier, -1, frame.points).astype(np.int64)
        self._w2c = np.array(w2c, np.float64)
        self._center = cam_center(self._w2c)
        self.conn: dict[int, int] = {}
        self.ordered: list[int] = []
        self.parent: int | None = None
        self.children: set[int] = set()
        self.loop_edges: set[int] = set()
        self.bad = False
        self.bow: dict[int, float] = {}
        self.words: np.ndarray = np.zeros(0, np.int64)  # visual word per keypoint
        self.protected = False  # loop closing in progress: no culling

    @property
    def w2c(self) -> np.ndarray:
        """World-to-camera [4,4]; assign a new matrix to move the keyframe (the centre is cached)."""
        return self._w2c

    @w2c.setter
    def w2c(self, value: np.ndarray) -> None:
        self._w2c = np.array(value, np.float64)
        self._center = cam_center(self._w2c)

    @property
    def center(self) -> np.ndarray:
        return self._center

    def __len__(self) -> int:
        return len(self.kp)

    def covisible(self, n: int | None = None) -> list[int]:
        return self.ordered[:n] if n is not None else list(self.ordered)


@dataclass
class CulledKeyFrame:
    """A keyframe removed from the map: pose relative to its parent (w2c_kf @ c2w_parent)."""

    kf_id: int
    frame_index: int
    parent: int
    rel: np.ndarray


class Map:
    """Keyframes + map points. All mutation happens under `lock` (an RLock) in threaded mode."""

    def __init__(self, scales: np.ndarray, capacity: int = 4096):
        self.scales = np.asarray(scales, np.float64)
        self.log_scale = float(np.log(self.scales[1])) if len(self.scales) > 1 else 1.0
        self.lock = threading.RLock()
        self._empty(capacity)

    def clear(self, capacity: int = 4096) -> None:
        """Drop every keyframe and point (a rejected monocular initial map); keyframe ids keep
        counting (never reused) and the lock stays (its holder may be inside it)."""
        next_id = self.next_kf_id
        self._empty(capacity)
        self.next_kf_id = next_id

    def _empty(self, capacity: int) -> None:
        self.kfs: dict[int, KeyFrame] = {}
        self.culled: dict[int, CulledKeyFrame] = {}
        self.next_kf_id = 0
        self.origin_kf: int | None = None
        self.version = 0  # bumps when point membership of keyframes changes
        self.n = 0
        self._alloc(capacity, keep=False)
        self.obs: list[dict[int, int]] = []

    # ----------------------------------------------------------------- point storage
    # the per-point arrays: name, shape of a row, dtype, value of an unused row
    POINT_ARRAYS = (
        ("pos", (3,), np.float64, 0), ("desc", (32,), np.uint8, 0), ("normal", (3,), np.float64, 0),
        ("dmin", (), np.float64, 0), ("dmax", (), np.float64, 0), ("visible", (), np.int64, 1),
        ("found", (), np.int64, 1), ("ref_kf", (), np.int64, -1), ("first_kf", (), np.int64, -1),
        ("color", (3,), np.float32, 0), ("valid", (), bool, False), ("emitted", (), bool, False),
        ("replaced", (), np.int64, -1),
        ("n_obs", (), np.int64, 0),  # observations, stereo / RGB-D ones counting 2 (ORB-SLAM nObs)
        ("ba_kf", (), np.int64, -1),
    )

    def _alloc(self, cap: int, keep: bool = True) -> None:
        """(Re)allocate the point arrays for cap points; keep: copy the current rows over."""
        for name, shape, dtype, fill in self.POINT_ARRAYS:
            old = getattr(self, name, None) if keep else None
            new = np.full((cap,) + shape, fill, dtype)
            if old is not None:
                new[: len(old)] = old
            setattr(self, name, new)
        self.cap = cap

    def add_points(self, pos: np.ndarray, kf: KeyFrame, kp_idx: np.ndarray, geometry: bool = True) -> np.ndarray:
        """New points at pos [M,3] observed by kf at keypoints kp_idx [M] -> ids [M].
        geometry=False leaves update_geometry to the caller (who adds more observations first)."""
        m = len(pos)
        if self.n + m > self.cap:
            self._alloc(max(2 * self.cap, self.n + m))
        ids = np.arange(self.n, self.n + m)
        self.n += m
        self.pos[ids] = pos
        self.desc[ids] = kf.kp.desc[kp_idx]
        self.color[ids] = kf.colors[kp_idx]
        self.ref_kf[ids] = kf.kf_id
        self.first_kf[ids] = kf.kf_id
        self.valid[ids] = True
        self.visible[ids] = 1
        self.found[ids] = 1
        self.n_obs[ids] = np.where(kf.ur[kp_idx] >= 0, 2, 1)
        self.obs.extend({kf.kf_id: int(i)} for i in kp_idx)
        kf.points[kp_idx] = ids
        if geometry:
            self.update_geometry(ids)
        self.version += 1
        return ids

    def add_obs(self, pid: int, kf: KeyFrame, idx: int) -> None:
        if kf.kf_id not in self.obs[pid]:
            self.obs[pid][kf.kf_id] = int(idx)
            self.n_obs[pid] += 2 if kf.ur[idx] >= 0 else 1
        kf.points[idx] = pid
        self.version += 1

    def erase_obs(self, pid: int, kf_id: int, min_obs: int = 1) -> None:
        """Remove kf_id's observation of pid; the point dies when fewer than min_obs remain."""
        o = self.obs[pid]
        idx = o.pop(kf_id, None)
        if idx is None:
            return
        kf = self.kfs.get(kf_id)
        self.n_obs[pid] -= 2 if kf is not None and kf.ur[idx] >= 0 else 1
        if kf is not None and kf.points[idx] == pid:
            kf.points[idx] = -1
        if self.ref_kf[pid] == kf_id and o:
            self.ref_kf[pid] = next(iter(o))
        if len(o) < min_obs:
            self.set_point_bad(pid)
        self.version += 1

    def set_point_bad(self, pid: int) -> None:
        for kf_id, idx in self.obs[pid].items():
            kf = self.kfs.get(kf_id)
            if kf is not None and kf.points[idx] == pid:
                kf.points[idx] = -1
        self.obs[pid] = {}
        self.n_obs[pid] = 0
        self.valid[pid] = False
        self.version += 1

    def replace_point(self, old: int, new: int, update_descriptor: bool = True) -> None:
        """Merge point `old` into `new` (fusion of duplicates). update_descriptor=False leaves the
        distinctive descriptor of `new` to the caller (batched after a fusion pass)."""
        if old == new or not self.valid[old] or not self.valid[new]:
            return
        for kf_id, idx in list(self.obs[old].items()):
            kf = self.kfs.get(kf_id)
            if kf is None:
                continue
            if kf_id in self.obs[new]:
                kf.points[idx] = -1
            else:
                self.obs[new][kf_id] = idx
                self.n_obs[new] += 2 if kf.ur[idx] >= 0 else 1
                kf.points[idx] = new
        self.visible[new] += self.visible[old]
        self.found[new] += self.found[old]
        self.obs[old] = {}
        self.n_obs[old] = 0
        self.valid[old] = False
        self.replaced[old] = new
        self.version += 1
        if update_descriptor:
            self.update_descriptors(np.array([new]))

    def observe(self, kf: KeyFrame, idx: np.ndarray, pids: np.ndarray, native: bool = True) -> None:
        """kf observes the valid points pids [K] at its keypoints idx [K], in order: an observation
        is added where kf has none of the point; a keypoint whose point kf already observes at
        another keypoint is cleared (kf.points = -1). native: the C++ loop where built."""
        ext = kernels() if native else None
        if ext is None:
            for i, p in zip(idx.tolist(), pids.tolist()):
                if kf.kf_id in self.obs[p]:
                    if self.obs[p][kf.kf_id] != i:
                        kf.points[i] = -1
                else:
                    self.add_obs(p, kf, i)
            return
        status = ext.observe_points(self.obs, pids, idx, int(kf.kf_id))
        add = status == 2
        kf.points[idx[status == 1]] = -1
        ia, pa = idx[add], pids[add]  # each point once: a second entry finds the first's observation
        kf.points[ia] = pa
        self.n_obs[pa] += np.where(kf.ur[ia] >= 0, 2, 1)
        self.version += len(pa)

    def live_ids(self, pids: np.ndarray) -> np.ndarray:
        """`live` of each of pids [K] (>= 0) -> [K] surviving point ids (-1: none)."""
        p = np.array(pids, np.int64)
        while True:
            dead = np.flatnonzero((p >= 0) & ~self.valid[np.maximum(p, 0)])
            if not len(dead):
                return p
            p[dead] = self.replaced[p[dead]]

    def live(self, pid: int) -> int:
        """Follow replacements to the surviving point (or -1)."""
        while pid >= 0 and not self.valid[pid]:
            pid = int(self.replaced[pid])
        return pid

    # ----------------------------------------------------------------- point statistics
    def update_geometry(self, pids: np.ndarray) -> None:
        """Viewing normal (mean direction from the observing cameras) and scale-invariance range."""
        pids = np.asarray(pids, np.int64)
        if len(pids) == 0:
            return
        owner, kfid, refs = self.observers(pids)
        if not len(owner):
            return
        ids, inv = np.unique(kfid, return_inverse=True)
        centers = np.stack([self.kfs[int(k)].center for k in ids])
        v = self.pos[pids][owner] - centers[inv]
        v /= np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)
        # per-point sums in observation order (what np.add.at does, at a fraction of its cost)
        n = np.stack([np.bincount(owner, weights=v[:, c], minlength=len(pids)) for c in range(3)], axis=1)
        norm = np.linalg.norm(n, axis=1)
        has = norm > 0
        self.normal[pids[has]] = n[has] / norm[has, None]
        # scale range from the reference keyframe's observation (refs >= 0: that keyframe is in
        # the map and sees the point, so it is among ids)
        ok = refs >= 0
        if ok.any():
            sel = pids[ok]
            cref = centers[np.searchsorted(ids, self.ref_kf[sel])]
            dist = np.linalg.norm(self.pos[sel] - cref, axis=1)
            self.dmax[sel] = dist * self.scales[refs[ok]]
            self.dmin[sel] = self.dmax[sel] / self.scales[-1]

    def unobserved_by(self, pids: np.ndarray, kf_id: int, native: bool = True) -> np.ndarray:
        """Which of the points pids [P] keyframe kf_id does not observe -> [P] bool (the C++ loop
        where built)."""
        ext = kernels() if native else None
        if ext is not None:
            return ext.unobserved_by(self.obs, pids, int(kf_id))
        return np.fromiter((kf_id not in self.obs[p] for p in pids.tolist()), bool, len(pids))

    def observers(self, pids: np.ndarray, native: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Observations of points pids [P] by keyframes of the map -> (row in pids [O], keyframe
        id [O]) in dict order, and per point the octave of its reference keyframe's observation
        [P] (-1: that keyframe is gone or does not see it). native: the C++ loop where built."""
        ext = kernels() if native else None
        if ext is not None:
            octaves = {k: kf.kp.octave for k, kf in self.kfs.items()}
            return ext.gather_observers(self.obs, pids, octaves, self.ref_kf[pids])
        owner, kfid = [], []
        for j, pid in enumerate(pids.tolist()):
            for k in self.obs[pid]:
                if k in self.kfs:
                    owner.append(j)
                    kfid.append(k)
        refs = self.ref_kf[pids].copy()
        for j, (pid, r) in enumerate(zip(pids.tolist(), refs.tolist())):
            ref = self.kfs.get(r)
            idx = self.obs[pid].get(r) if ref is not None else None
            refs[j] = -1 if idx is None else ref.kp.octave[idx]
        return np.asarray(owner, np.int64), np.asarray(kfid, np.int64), refs

    def update_descriptors(self, pids: np.ndarray, native: bool = True) -> None:
        """Distinctive descriptor: the observation's descriptor with the least median distance.

        The C++ kernel (segs.slam.native) where it is built; otherwise the observations'
        descriptors are gathered per keyframe and the distances computed per group of points with
        the same number of observations (vectorized numpy). Same result either way.
        """
        pids = np.asarray(pids, np.int64)
        obs = self.obs
        ext = kernels() if native else None
        if ext is not None:
            descs = {k: kf.kp.desc for k, kf in self.kfs.items()}
            rows, desc = ext.distinctive_descriptors(obs, pids, descs)
            self.desc[pids[rows]] = desc
            return
        counts = np.array([len(obs[p]) for p in pids.tolist()], np.int64)
        owner = np.repeat(np.flatnonzero(counts >= 2), counts[counts >= 2])  # [O] row of pids
        if not len(owner):
            return
        flat = chain.from_iterable(chain.from_iterable(obs[p].items() for p in pids[counts >= 2].tolist()))
        kf_of, kp_of = np.fromiter(flat, np.int64, 2 * len(owner)).reshape(-1, 2).T  # (kf, keypoint), point-major
        alive = np.isin(kf_of, np.fromiter(self.kfs, np.int64, len(self.kfs)))
        if not alive.all():  # observations of removed keyframes do not vote
            owner, kf_of, kp_of = owner[alive], kf_of[alive], kp_of[alive]
        rows, counts = np.unique(owner, return_counts=True)
        if not (counts >= 2).all():
            two = np.isin(owner, rows[counts >= 2])
            owner, kf_of, kp_of = owner[two], kf_of[two], kp_of[two]
            rows, counts = rows[counts >= 2], counts[counts >= 2]
        if not len(rows):
            return
        pts = pids[rows]
        desc = np.empty((len(kf_of), 32), np.uint8)  # [O,32] observation descriptors, point-major
        by_kf = np.argsort(kf_of, kind="stable")
        ks, first = np.unique(kf_of[by_kf], return_index=True)
        for k, sel in zip(ks.tolist(), np.split(by_kf, first[1:])):
            desc[sel] = self.kfs[k].kp.desc[kp_of[sel]]
        starts = np.cumsum(counts) - counts
        for n in np.unique(counts).tolist():
            g = counts == n
            d = desc[starts[g][:, None] + np.arange(n)]  # [P,n,32]
            d64 = d.view(np.uint64)  # [P,n,4]
            dm = np.sort(np.bitwise_count(d64[:, :, None, :] ^ d64[:, None, :, :]).sum(-1), axis=2)  # [P,n,n]
            median = dm[:, :, (n - 1) // 2] + dm[:, :, n // 2]  # 2x the median (np.median's mean of the middle two)
            best = np.argmin(median, axis=1)
            self.desc[pts[g]] = d[np.arange(int(g.sum())), best]

    def predict_level(self, pids: np.ndarray, dist: np.ndarray) -> np.ndarray:
        """Predicted pyramid level [M] for points pids viewed from distance dist [M]."""
        ratio = self.dmax[pids] / np.maximum(dist, 1e-9)
        lvl = np.ceil(np.log(np.maximum(ratio, 1e-9)) / self.log_scale)
        return np.clip(lvl, 0, len(self.scales) - 1).astype(np.int64)

    # ----------------------------------------------------------------- keyframes
    def new_kf_id(self) -> int:
        k = self.next_kf_id
        self.next_kf_id += 1
        return k

    def add_keyframe(self, kf: KeyFrame) -> None:
        self.kfs[kf.kf_id] = kf
        if self.origin_kf is None:
            self.origin_kf = kf.kf_id
        self.version += 1

    def kf_point_ids(self, kf: KeyFrame) -> np.ndarray:
        """Valid map points of kf -> (keypoint indices [K], point ids [K])."""
        idx = np.flatnonzero(kf.points >= 0)
        pid = kf.points[idx]
        ok = self.valid[pid]
        return idx[ok], pid[ok]

    def count_observers(self, pids: np.ndarray, exclude: int = -1, native: bool = True) -> dict[int, int]:
        """Keyframe id (other than exclude) -> how many of the points pids [P] it observes, in
        first-seen order (the C++ loop where built)."""
        ext = kernels() if native else None
        if ext is not None:
            keys, cnt = ext.count_observers(self.obs, pids, int(exclude))
            return dict(zip(keys.tolist(), cnt.tolist()))
        counts: dict[int, int] = {}
        for pid in pids.tolist():
            for k in self.obs[pid]:
                if k != exclude:
                    counts[k] = counts.get(k, 0) + 1
        return counts

    def update_connections(self, kf: KeyFrame, th: int = 15) -> None:
        """Covisibility weights (shared points) with every keyframe; spanning-tree parent."""
        counts = self.count_observers(self.kf_point_ids(kf)[1], kf.kf_id)
        counts = {k: c for k, c in counts.items() if k in self.kfs and not self.kfs[k].bad}
        if not counts:
            return
        kmax = max(counts, key=lambda k: (counts[k], -k))
        conn = {k: c for k, c in counts.items() if c >= th} or {kmax: counts[kmax]}
        for k, c in conn.items():
            other = self.kfs[k]
            other.conn[kf.kf_id] = c
            self._order(other)
        kf.conn = conn
        self._order(kf)
        if kf.parent is None and kf.kf_id != self.origin_kf:
            kf.parent = kmax
            self.kfs[kmax].children.add(kf.kf_id)

    @staticmethod
    def _order(kf: KeyFrame) -> None:
        kf.ordered = sorted(kf.conn, key=lambda k: (-kf.conn[k], k))

    def erase_connection(self, kf: KeyFrame, other: int) -> None:
        if kf.conn.pop(other, None) is not None:
            self._order(kf)

    def set_kf_bad(self, kf: KeyFrame) -> None:
        """Cull a keyframe: drop its observations, re-parent its children (ORB-SLAM's rule)."""
        if kf.kf_id == self.origin_kf or kf.bad:
            return
        for k in list(kf.conn):
            if k in self.kfs:
                self.erase_connection(self.kfs[k], kf.kf_id)
        idx, pids = self.kf_point_ids(kf)
        for pid in pids:
            self.erase_obs(int(pid), kf.kf_id)
        self._reparent_children(kf)
        parent = self.kfs.get(kf.parent) if kf.parent is not None else None
        if parent is not None:
            parent.children.discard(kf.kf_id)
            self.culled[kf.kf_id] = CulledKeyFrame(kf.kf_id, kf.frame_index, parent.kf_id,
                                                   kf.w2c @ inv_se3(parent.w2c))
        kf.bad = True
        kf.conn = {}
        kf.ordered = []
        del self.kfs[kf.kf_id]
        self.version += 1

    def _reparent_children(self, kf: KeyFrame) -> None:
        candidates = {kf.parent} if kf.parent is not None else set()
        children = {c for c in kf.children if c in self.kfs}
        while children:
            best = None
            for c in children:
                ch = self.kfs[c]
                for k, w in ch.conn.items():
                    if k in candidates and (best is None or w > best[2]):
                        best = (c, k, w)
            if best is None:
                break
            c, k, _ = best
            self.kfs[c].parent = k
            self.kfs[k].children.add(c)
            candidates.add(c)
            children.discard(c)
        for c in children:  # no covisible candidate: attach to the culled kf's parent
            self.kfs[c].parent = kf.parent
            if kf.parent in self.kfs:
                self.kfs[kf.parent].children.add(c)

    def kf_pose(self, kf_id: int) -> np.ndarray | None:
        """w2c of a live keyframe, or of a culled one recomposed through its parents."""
        rel = np.eye(4)
        seen = set()
        while kf_id not in self.kfs:
            c = self.culled.get(kf_id)
            if c is None or kf_id in seen:
                return None
            seen.add(kf_id)
            rel = rel @ c.rel
            kf_id = c.parent
        return rel @ self.kfs[kf_id].w2c

    def keyframe_poses(self, kf_ids: list[int]) -> dict[int, np.ndarray]:
        """kf_id -> w2c [4,4] (copies) of live keyframes and of culled ones, recomposed from their
        parent (ORB-SLAM's Tcp); unknown ids are left out."""
        out = {}
        for k in kf_ids:
            if k in self.kfs:
                out[k] = self.kfs[k].w2c.copy()
            elif k in self.culled:
                T = self.kf_pose(k)
                if T is not None:
                    out[k] = T
        return out

    def take_new_points(self, pids: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The valid points among pids not handed out before, marked as handed out ->
        (positions [M,3] float64, colours [M,3] float32, creating keyframe [M] int64), or None."""
        pids = np.asarray(pids, np.int64)
        pids = pids[self.valid[pids] & ~self.emitted[pids]]
        if len(pids) == 0:
            return None
        self.emitted[pids] = True
        return self.pos[pids].copy(), self.color[pids].copy(), self.first_kf[pids].copy()

    def live_ancestor(self, kf_id: int) -> int | None:
        while kf_id not in self.kfs:
            c = self.culled.get(kf_id)
            if c is None:
                return None
            kf_id = c.parent
        return kf_id
