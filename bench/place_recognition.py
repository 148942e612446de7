"""Place recognition with BoW vocabularies on real 7-Scenes frames (in no vocabulary's training set).

    python bench/place_recognition.py                                  # the shipped vocabulary
    python bench/place_recognition.py --vocabulary a.npz b.npz         # several, same protocol

Protocol (deterministic): 7-Scenes redkitchen frames 0-599 (640x480, Kinect RGB-D, KinectFusion
poses). Database: frames 0, 10, ..., 590; queries: the other frames (every --query-step-th).
Each query is matched
against the database frames at least --gap frames (default 100, 3.3 s) away from it, as loop
detection would (not its recent past). Ground truth from depth and poses: a database frame is a
true match when each of the two frames sees at least --min-overlap (half) of the other's valid
depth pixels (every 8th pixel) at a consistent depth (|dz| < 5 % + 2 cm). Queries with no true
match are left out. Retrieval: `KeyFrameDatabase.query`, DBoW2 L1 scores of tf-idf vectors of the
ORB features (the frontend's extractor, 1,500 features). recall@k: share of queries with a true
match among the k best; chance@1: the recall@1 of a random pick. JSON with --json.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import _harness

_harness.apply_process_settings()  # before torch loads

import numpy as np

from segs.data.tum import TumSequence
from segs.slam.features.extractor import OrbExtractor, to_gray
from segs.slam.map.vocabulary import KeyFrameDatabase, Vocabulary

DATA = _harness.SEVEN_SCENES
# the ground truth reprojects depth images: the 7-Scenes depth camera's intrinsics (the colour
# camera's differ, and ORB retrieval needs none)
DEPTH_K = np.array([[585.0, 0, 320], [0, 585.0, 240], [0, 0, 1]])


def open_7scenes(root: Path = DATA) -> TumSequence:
    """The 7-Scenes frames through the TUM reader (intrinsics and depth scale of 7-Scenes)."""
    return TumSequence(root=str(root), sensor="rgbd", intrinsics=[585, 585, 320, 240], depth_scale=1000)


def seen_share(depth_a: np.ndarray, c2w_a: np.ndarray, depth_b: np.ndarray, c2w_b: np.ndarray,
               K: np.ndarray, step: int = 8) -> float:
    """Share of a's valid depth pixels (every step-th, [H,W] metres) that b sees at a consistent
    depth (|dz| < 5 % + 2 cm); c2w_* [4,4] camera-to-world, K [3,3]."""
    v, u = np.mgrid[0:depth_a.shape[0]:step, 0:depth_a.shape[1]:step]
    z = depth_a[v, u]
    ok = z > 0
    if not ok.any():
        return 0.0
    pa = np.stack([(u[ok] - K[0, 2]) / K[0, 0] * z[ok], (v[ok] - K[1, 2]) / K[1, 1] * z[ok], z[ok]], 1)
    rel = np.linalg.inv(c2w_b) @ c2w_a
    pb = pa @ rel[:3, :3].T + rel[:3, 3]
    zb = pb[:, 2]
    front = zb > 0.1
    ub = np.round(pb[:, 0] / np.where(front, zb, 1) * K[0, 0] + K[0, 2]).astype(int)
    vb = np.round(pb[:, 1] / np.where(front, zb, 1) * K[1, 1] + K[1, 2]).astype(int)
    inside = front & (ub >= 0) & (ub < depth_b.shape[1]) & (vb >= 0) & (vb < depth_b.shape[0])
    db = np.zeros_like(zb)
    db[inside] = depth_b[vb[inside], ub[inside]]
    good = inside & (db > 0) & (np.abs(db - zb) < 0.05 * zb + 0.02)
    return float(good.mean())


def protocol(seq, db_step: int = 10, query_step: int = 1, gap: int = 100, min_overlap: float = 0.5,
             frames: int = 600) -> dict:
    """Frames, ORB descriptors and ground truth of the protocol above ->
    {"database": [D], "queries": {q: [database frames at least gap away]}, "true": {q: set},
    "desc": {frame: [N,32] uint8}} (queries without a true match left out)."""
    ex = OrbExtractor()
    database = list(range(0, frames, db_step))
    queries = [q for q in range(1, frames, query_step) if q % db_step]
    K = DEPTH_K
    data = {}
    for i in database + queries:
        f = seq[i]
        data[i] = (f.depth, f.pose_c2w, ex.extract(to_gray(f.rgb)).desc)
    cands, true = {}, {}
    for q in queries:
        c = [d for d in database if abs(d - q) >= gap]
        t = {d for d in c if min(seen_share(data[q][0], data[q][1], data[d][0], data[d][1], K),
                                 seen_share(data[d][0], data[d][1], data[q][0], data[q][1], K)) >= min_overlap}
        if t:
            cands[q], true[q] = c, t
    return {"database": database, "queries": cands, "true": true, "desc": {i: v[2] for i, v in data.items()}}


def recall(voc: Vocabulary, p: dict, ks: tuple[int, ...] = (1, 5)) -> dict:
    """recall@k of KeyFrameDatabase queries with vocabulary voc on protocol p -> {"recall@k": ..,
    "chance@1": .., "queries": n}."""
    kfdb = KeyFrameDatabase()
    for d in p["database"]:
        kfdb.add(d, voc.bow(voc.words(p["desc"][d])))
    hits = {k: 0 for k in ks}
    chance = []
    for q, cands in p["queries"].items():
        exclude = set(p["database"]) - set(cands)
        ranked = [kf for kf, _ in kfdb.query(voc.bow(voc.words(p["desc"][q])), max(ks), exclude)]
        for k in ks:
            hits[k] += bool(set(ranked[:k]) & p["true"][q])
        chance.append(len(p["true"][q]) / len(cands))
    n = len(p["queries"])
    out = {f"recall@{k}": hits[k] / n for k in ks}
    out.update({"chance@1": float(np.mean(chance)), "queries": n})
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--vocabulary", nargs="*", default=[None], help=".npz files (default: the shipped one)")
    ap.add_argument("--data", default=str(DATA))
    ap.add_argument("--gap", type=int, default=100)
    ap.add_argument("--query-step", type=int, default=1)
    ap.add_argument("--min-overlap", type=float, default=0.5)
    ap.add_argument("--json", default=None, help="also write the results here")
    a = ap.parse_args()
    if not Path(a.data).is_dir():
        sys.exit(f"error: {a.data}: 7-Scenes folder not found")
    p = protocol(open_7scenes(Path(a.data)), query_step=a.query_step, gap=a.gap, min_overlap=a.min_overlap)
    rows = []
    for path in a.vocabulary:
        voc = Vocabulary.load(path)
        r = {"vocabulary": path or "shipped", "words": voc.n_words, **recall(voc, p)}
        rows.append(r)
        print(f"{r['vocabulary']}: {r['words']} words, {r['queries']} queries, recall@1 {r['recall@1']:.3f}, "
              f"recall@5 {r['recall@5']:.3f} (chance@1 {r['chance@1']:.3f})")
    if a.json:
        _harness.write_json(a.json, rows)


if __name__ == "__main__":
    main()
