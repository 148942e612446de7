"""The ORB frontend's checkpoint state as explicit arrays and dicts (format segs.state.v3).

`encode(parts)` turns the live parts of an OrbFrontend (map, keyframe database, outbox and the
state fields of its tracker, local mapping and loop closing: `StateFields.state_fields()`) into
numbers, strings, numpy arrays, lists and dicts, no class instance; `decode(state)` builds the
parts again. Dict and set orders are kept (a set as the list of its iteration order, rebuilt by
inserting in that order, as pickle does), so a resumed frontend tracks exactly as the one that
was saved. Keys are Python ints (the C++ kernels read the observation dicts).

Checkpoints of the earlier formats ("segs.orb.v1", "segs.orb.v2": pickled Map, KeyFrameDatabase,
MapOutbox and components, possibly under the modules' former names) are converted by
`from_legacy`: unpickled into the current classes, then the same live parts.
"""
from __future__ import annotations

import copy
import io
import pickle
import threading
from dataclasses import asdict
from typing import Any, Mapping

import numpy as np

from segs.data.frame import Camera
from segs.errors import ConfigError
from segs.slam.base import STATE_FORMAT
from segs.slam.features.extractor import Keypoints
from segs.slam.features.frame import KeypointGrid, SlamFrame
from segs.slam.geometry import cam_center
from segs.slam.map.map import CulledKeyFrame, KeyFrame, Map
from segs.slam.map.vocabulary import KeyFrameDatabase
from segs.slam.outbox import MapOutbox
from segs.slam.tracking.frame_poses import FramePose, FramePoses

KIND = "orb"
LEGACY_FORMATS = ("segs.orb.v1", "segs.orb.v2")


def encode(parts: Mapping[str, Any]) -> dict:
    """parts: map, kfdb, outbox (live objects), tracker, local_mapping, loop (state fields) -> the
    state, a copy (the frontend goes on changing its arrays in place)."""
    return copy.deepcopy(_encode(parts))


def _encode(parts: Mapping[str, Any]) -> dict:
    return {"format": STATE_FORMAT, "kind": KIND, "map": _map(parts["map"]), "kfdb": _kfdb(parts["kfdb"]),
            "outbox": parts["outbox"].state_dict(), "tracker": _tracker(parts["tracker"]),
            "local_mapping": {"recent": np.array(parts["local_mapping"]["recent"], np.int64),
                              "ba_times": np.array(parts["local_mapping"]["ba_times"], np.float64)},
            "loop": _loop(parts["loop"])}  # fmt: skip


def decode(state: Mapping[str, Any]) -> dict:
    """A state of encode() (or of an earlier format, converted) -> the live parts (sharing no
    array with `state`, which may be loaded again)."""
    fmt = state.get("format")
    if fmt in LEGACY_FORMATS:
        return from_legacy(state)
    if fmt != STATE_FORMAT or state.get("kind") != KIND:
        raise ConfigError(f"slam: the checkpoint's frontend state is {state.get('kind') or fmt!r}, not an OrbFrontend "
                          f"state ({STATE_FORMAT}); resume with the frontend that wrote it")  # fmt: skip
    state = copy.deepcopy(state)
    lm, loop = state["local_mapping"], state["loop"]
    return {"map": _map_from(state["map"]), "kfdb": _kfdb_from(state["kfdb"]),
            "outbox": MapOutbox.from_state(state["outbox"]), "tracker": _tracker_from(state["tracker"]),
            "local_mapping": {"recent": lm["recent"].tolist(), "ba_times": lm["ba_times"].tolist()},
            "loop": {"groups": [(set(g["kfs"].tolist()), int(g["count"])) for g in loop["groups"]],
                     "last_loop_kf": int(loop["last_loop_kf"]), "loops": [tuple(p) for p in loop["loops"].tolist()]}}  # fmt: skip


# -------------------------------------------------------------------- features and keyframes
def _keypoints(kp: Keypoints) -> dict:
    return {"uv": kp.uv, "octave": kp.octave, "angle": kp.angle, "response": kp.response, "desc": kp.desc}


def _grid(grid: KeypointGrid) -> dict:
    return {"cell": grid.cell, "nx": grid.nx, "ny": grid.ny, "order": grid.order, "start": grid.start}


def _grid_from(d: Mapping, uv: np.ndarray) -> KeypointGrid:
    grid = KeypointGrid.__new__(KeypointGrid)
    grid.cell, grid.nx, grid.ny, grid.order, grid.start, grid.uv = d["cell"], d["nx"], d["ny"], d["order"], d["start"], uv
    return grid


FRAME_FIELDS = ("index", "timestamp", "kp", "depth", "ur", "colors", "camera", "bf", "grid", "points", "outlier", "w2c",
                "ref_kf", "build_seconds")  # fmt: skip


def _frame(f: SlamFrame | None) -> dict | None:
    if f is None:
        return None
    out = {k: getattr(f, k) for k in FRAME_FIELDS}
    out.update(kp=_keypoints(f.kp), grid=_grid(f.grid), camera=asdict(f.camera), build_seconds=list(f.build_seconds))
    return out


def _frame_from(d: Mapping | None) -> SlamFrame | None:
    if d is None:
        return None
    kp = Keypoints(**d["kp"])
    values = {**d, "kp": kp, "grid": _grid_from(d["grid"], kp.uv), "camera": Camera(**d["camera"]),
              "build_seconds": tuple(d["build_seconds"])}  # fmt: skip
    return SlamFrame(**{k: values[k] for k in FRAME_FIELDS})


KEYFRAME_FIELDS = ("kf_id", "frame_index", "timestamp", "kp", "depth", "ur", "colors", "grid", "points", "_w2c", "_center",
                   "conn", "ordered", "parent", "children", "loop_edges", "bad", "bow", "words", "protected")  # fmt: skip


def _keyframe(kf: KeyFrame) -> dict:
    return {"kf_id": kf.kf_id, "frame_index": kf.frame_index, "timestamp": kf.timestamp, "kp": _keypoints(kf.kp),
            "depth": kf.depth, "ur": kf.ur, "colors": kf.colors, "grid": _grid(kf.grid), "points": kf.points,
            "w2c": kf.w2c, "conn": _int_dict(kf.conn), "ordered": np.array(kf.ordered, np.int64), "parent": kf.parent,
            "children": np.array(list(kf.children), np.int64), "loop_edges": np.array(list(kf.loop_edges), np.int64),
            "bad": kf.bad, "bow": {"word": np.array(list(kf.bow), np.int64), "weight": np.array(list(kf.bow.values()))},
            "words": kf.words, "protected": kf.protected}  # fmt: skip


def _keyframe_from(d: Mapping) -> KeyFrame:
    kf = KeyFrame.__new__(KeyFrame)
    kp = Keypoints(**d["kp"])
    kf.kf_id, kf.frame_index, kf.timestamp = int(d["kf_id"]), int(d["frame_index"]), d["timestamp"]
    kf.kp, kf.depth, kf.ur, kf.colors, kf.grid, kf.points = kp, d["depth"], d["ur"], d["colors"], _grid_from(d["grid"], kp.uv), d["points"]
    kf._w2c = d["w2c"]
    kf._center = cam_center(kf._w2c)
    kf.conn, kf.ordered = _int_dict_from(d["conn"]), d["ordered"].tolist()
    kf.parent = None if d["parent"] is None else int(d["parent"])
    kf.children, kf.loop_edges = set(d["children"].tolist()), set(d["loop_edges"].tolist())
    kf.bad, kf.protected, kf.words = bool(d["bad"]), bool(d["protected"]), d["words"]
    kf.bow = dict(zip(d["bow"]["word"].tolist(), d["bow"]["weight"].tolist()))
    return kf


def _int_dict(d: Mapping[int, int]) -> dict:
    return {"key": np.array(list(d), np.int64), "value": np.array(list(d.values()), np.int64)}


def _int_dict_from(d: Mapping) -> dict[int, int]:
    return dict(zip(d["key"].tolist(), d["value"].tolist()))


# -------------------------------------------------------------------- map and keyframe database
def _map(m: Map) -> dict:
    """Keyframes, culled keyframes, counters, the point arrays' used rows and the observations
    (flattened in order: per point its count, then (kf_id, keypoint) pairs)."""
    n = m.n
    obs = m.obs[:n]
    culled = list(m.culled.values())
    return {
        "scales": m.scales, "cap": m.cap, "n": n, "next_kf_id": m.next_kf_id, "origin_kf": m.origin_kf, "version": m.version,
        "keyframes": [_keyframe(kf) for kf in m.kfs.values()],
        "culled": {"kf_id": np.array([c.kf_id for c in culled], np.int64),
                   "frame_index": np.array([c.frame_index for c in culled], np.int64),
                   "parent": np.array([c.parent for c in culled], np.int64),
                   "rel": np.array([c.rel for c in culled], np.float64).reshape(-1, 4, 4)},
        "points": {name: getattr(m, name)[:n].copy() for name, *_ in Map.POINT_ARRAYS},
        "obs_count": np.fromiter(map(len, obs), np.int64, n),
        "obs": np.fromiter((v for o in obs for kv in o.items() for v in kv), np.int64).reshape(-1, 2),
    }  # fmt: skip


def _map_from(d: Mapping) -> Map:
    m = Map(d["scales"], capacity=int(d["cap"]))
    n = m.n = int(d["n"])
    m.next_kf_id, m.version = int(d["next_kf_id"]), int(d["version"])
    m.origin_kf = None if d["origin_kf"] is None else int(d["origin_kf"])
    for name, *_ in Map.POINT_ARRAYS:
        getattr(m, name)[:n] = d["points"][name]
    m.kfs = {kf.kf_id: kf for kf in map(_keyframe_from, d["keyframes"])}
    c = d["culled"]
    m.culled = {int(k): CulledKeyFrame(int(k), int(i), int(p), r)
                for k, i, p, r in zip(c["kf_id"], c["frame_index"], c["parent"], c["rel"])}  # fmt: skip
    pairs = iter(d["obs"].tolist())
    m.obs = [dict(next(pairs) for _ in range(count)) for count in d["obs_count"].tolist()]
    return m


def _kfdb(db: KeyFrameDatabase) -> dict:
    """The inverted index (per word its keyframes, in set order) and every keyframe's bag of words."""
    words = list(db.index)
    bows = list(db.bows.items())
    return {"word": np.array(words, np.int64), "word_count": np.array([len(db.index[w]) for w in words], np.int64),
            "word_kfs": np.array([k for w in words for k in db.index[w]], np.int64),
            "bow_kf": np.array([k for k, _ in bows], np.int64), "bow_words": [b[0] for _, b in bows],
            "bow_weights": [b[1] for _, b in bows]}  # fmt: skip


def _kfdb_from(d: Mapping) -> KeyFrameDatabase:
    db = KeyFrameDatabase()
    kfs = iter(d["word_kfs"].tolist())
    for w, count in zip(d["word"].tolist(), d["word_count"].tolist()):
        s = db.index[w] = set()
        for _ in range(count):
            s.add(next(kfs))
    db.bows = {k: (words, weights) for k, words, weights in zip(d["bow_kf"].tolist(), d["bow_words"], d["bow_weights"])}
    return db


# -------------------------------------------------------------------- the components' state fields
def _frame_poses(p: FramePoses) -> dict:
    """Per tracked frame (dict order): kind 0 keyframe itself, 1 relative to kf_id, 2 absolute w2c."""
    recs = list(p.poses.items())
    kind = [0 if r.kf_id is not None and r.rel is None else 1 if r.kf_id is not None else 2 for _, r in recs]
    pose = [np.eye(4) if k == 0 else r.rel if k == 1 else r.w2c for k, (_, r) in zip(kind, recs)]
    return {"frame": np.array([i for i, _ in recs], np.int64), "kind": np.array(kind, np.int8),
            "kf_id": np.array([-1 if r.kf_id is None else r.kf_id for _, r in recs], np.int64),
            "pose": np.array(pose, np.float64).reshape(-1, 4, 4), "lost": np.array(sorted(p.lost), np.int64),
            "kf_frames": _int_dict(p.kf_frames)}  # fmt: skip


def _frame_poses_from(d: Mapping) -> FramePoses:
    poses = {}
    for i, kind, k, pose in zip(d["frame"].tolist(), d["kind"].tolist(), d["kf_id"].tolist(), d["pose"]):
        poses[i] = FramePose(k) if kind == 0 else FramePose(k, rel=pose) if kind == 1 else FramePose(None, w2c=pose)
    return FramePoses(poses, set(d["lost"].tolist()), _int_dict_from(d["kf_frames"]))


TRACKER_FIELDS = ("poses", "state", "last", "velocity", "ref_kf", "last_kf_frame", "last_reloc_frame", "lost_since",
                  "last_good_w2c", "_local_key", "_local_kfs", "_local_pids", "_max_inl", "mono_init", "depth_retries",
                  "init_waited")  # fmt: skip


SCALARS = ("ref_kf", "last_kf_frame", "last_reloc_frame", "lost_since", "_max_inl", "init_waited")  # int or None


def _tracker(t: Mapping[str, Any]) -> dict:
    """The Tracker's state fields (its _STATE): records and frames encoded, the rest numbers / arrays."""
    out = {k: t[k] for k in TRACKER_FIELDS if k in t}
    out.update({k: None if t[k] is None else int(t[k]) for k in SCALARS if k in t})
    key = t.get("_local_key")
    init = t.get("mono_init")
    out.update(poses=_frame_poses(t["poses"]), state=str(getattr(t["state"], "value", t["state"])), last=_frame(t["last"]),
               _local_key=None if key is None else {"kfs": np.array(key[0], np.int64), "version": int(key[1])},
               _local_kfs=np.array(t.get("_local_kfs", []), np.int64),
               depth_retries=np.array(t.get("depth_retries", []), np.int64),
               mono_init=None if init is None else {"ref": _frame(init.ref), "waiting": [_frame(f) for f in init.waiting]})  # fmt: skip
    return out


def _tracker_from(d: Mapping[str, Any]) -> dict:
    out = dict(d)
    key, init = d["_local_key"], d["mono_init"]
    out.update(poses=_frame_poses_from(d["poses"]), last=_frame_from(d["last"]),
               _local_key=None if key is None else (tuple(key["kfs"].tolist()), int(key["version"])),
               _local_kfs=d["_local_kfs"].tolist(), depth_retries=d["depth_retries"].tolist(),
               mono_init=None if init is None else {"ref": _frame_from(init["ref"]),
                                                     "waiting": [_frame_from(f) for f in init["waiting"]]})  # fmt: skip
    return out


def _loop(lc: Mapping[str, Any]) -> dict:
    return {"groups": [{"kfs": np.array(list(g), np.int64), "count": int(c)} for g, c in lc["groups"]],
            "last_loop_kf": int(lc["last_loop_kf"]), "loops": np.array(lc["loops"], np.int64).reshape(-1, 2)}  # fmt: skip


# -------------------------------------------------------------------- earlier formats
# segs.slam's modules before its stages became subpackages -> where their classes live now: blobs
# written before the move name the old modules (a module whose name is now a package's, such as
# segs.slam.map, defines no class in the package's __init__)
MOVED_MODULES = {
    "segs.slam.features": "segs.slam.features.extractor",
    "segs.slam.stereo": "segs.slam.features.stereo",
    "segs.slam.frame": "segs.slam.features.frame",
    "segs.slam.map": "segs.slam.map.map",
    "segs.slam.vocabulary": "segs.slam.map.vocabulary",
    "segs.slam.matching": "segs.slam.estimation.matching",
    "segs.slam.optimize": "segs.slam.estimation.optimize",
    "segs.slam.tracking": "segs.slam.tracking.tracker",
    "segs.slam.initialization": "segs.slam.tracking.initialization",
    "segs.slam.frame_poses": "segs.slam.tracking.frame_poses",
    "segs.slam.keyframe_queue": "segs.slam.backend.keyframe_queue",
    "segs.slam.local_mapping": "segs.slam.backend.local_mapping",
    "segs.slam.loop_closing": "segs.slam.backend.loop_closing",
    "segs.slam.ba_process": "segs.slam.backend.ba_process",
}


class _MovedModulesUnpickler(pickle.Unpickler):
    """Finds the classes of a blob that names segs.slam modules by their former names (MOVED_MODULES)."""

    def find_class(self, module: str, name: str) -> Any:
        return super().find_class(MOVED_MODULES.get(module, module), name)


def from_legacy(state: Mapping[str, Any]) -> dict:
    """A "segs.orb.v2" state (pickled map, keyframe database, outbox and component state fields)
    or a "segs.orb.v1" one (the frontend's attributes: pickled Tracker / LocalMapper / LoopCloser,
    `_traj` tuples, `_lost`, `_kf_frames`, `_pending`, `_pending_pids`) -> the live parts."""
    data = _MovedModulesUnpickler(io.BytesIO(state["blob"])).load()
    if state["format"] == "segs.orb.v1":
        tracker = dict(vars(data["tracker"]))
        tracker["poses"] = FramePoses.from_legacy(data["_traj"], data["_lost"], data["_kf_frames"])
        data = {"map": data["map"], "kfdb": data["kfdb"], "outbox": MapOutbox(data["_pending"], data["_pending_pids"]),
                "tracker": tracker, "mapper": dict(vars(data["mapper"])), "loop": dict(vars(data["loop"]))}  # fmt: skip
    data["map"].lock = threading.RLock()
    tracker = dict(data["tracker"])
    init = tracker.get("mono_init")
    if init is not None:
        tracker["mono_init"] = {"ref": init.ref, "waiting": list(init.waiting)}
    return {"map": data["map"], "kfdb": data["kfdb"], "outbox": data["outbox"], "tracker": tracker,
            "local_mapping": dict(data["mapper"]), "loop": dict(data["loop"])}  # fmt: skip

