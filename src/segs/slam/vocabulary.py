"""Bag of binary words (DBoW2's idea) for place recognition: relocalization and loop detection.

A vocabulary tree of branching k and depth L is trained by hierarchical k-majority clustering of
ORB descriptors (k-means for Hamming space: centres are bitwise majority votes). Words are the
leaves; tf-idf weights, L1-normalised vectors and DBoW2's L1 score s = 1 - |v1 - v2|_1 / 2.

The shipped vocabulary (``vocab/orb_k8_l4.npz``, 4,096 words) was trained with
``python -m segs.slam.vocabulary`` from the ORB features of the repository's real images
(datasets/tum_fr3_cabinet_kf and datasets/euroc_v101_micro); see `train_from_images`.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from segs.slam.features import hamming_matrix

DEFAULT_PATH = Path(__file__).with_name("vocab") / "orb_k8_l4.npz"


def _majority(desc: np.ndarray) -> np.ndarray:
    """Bitwise majority of descriptors [N,32] uint8 -> [32] uint8."""
    bits = np.unpackbits(desc, axis=1)
    return np.packbits(bits.mean(0) >= 0.5)


def kmajority(desc: np.ndarray, k: int, rng: np.random.Generator, iters: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Cluster binary descriptors [N,32] into k centres -> (centres [k,32], labels [N])."""
    n = len(desc)
    if n <= k:
        centres = desc[np.arange(k) % max(n, 1)] if n else np.zeros((k, 32), np.uint8)
        return centres.copy(), np.arange(n)
    # k-means++ seeding in Hamming space
    idx = [int(rng.integers(n))]
    dmin = hamming_matrix(desc, desc[idx]).min(1).astype(np.float64)
    for _ in range(1, k):
        p = dmin ** 2
        p = p / p.sum() if p.sum() > 0 else np.full(n, 1.0 / n)
        idx.append(int(rng.choice(n, p=p)))
        dmin = np.minimum(dmin, hamming_matrix(desc, desc[idx[-1:]])[:, 0])
    centres = desc[idx].copy()
    labels = np.zeros(n, np.int64)
    for it in range(iters):
        new = hamming_matrix(desc, centres).argmin(1)
        if it and np.array_equal(new, labels):
            break
        labels = new
        for c in range(k):
            m = labels == c
            if m.any():
                centres[c] = _majority(desc[m])
    return centres, labels


class Vocabulary:
    """Vocabulary tree: centres per level ([k^l,32] for l = 1..L) and idf per word [k^L]."""

    def __init__(self, k: int, levels: list[np.ndarray], idf: np.ndarray):
        self.k = int(k)
        self.levels = [np.ascontiguousarray(c) for c in levels]
        self._lv64 = [c.view(np.uint64).reshape(-1, self.k, 4) for c in self.levels]
        self.idf = np.asarray(idf, np.float64)
        self.n_words = len(self.idf)

    # --------------------------------------------------------------- training / io
    @classmethod
    def train(cls, desc: np.ndarray, n_images: np.ndarray, k: int = 8, depth: int = 4,
              seed: int = 0) -> "Vocabulary":
        """desc [N,32] training descriptors, n_images [N] image index of each (for the idf)."""
        rng = np.random.default_rng(seed)
        levels: list[np.ndarray] = []
        groups = [np.arange(len(desc))]
        for _ in range(depth):
            centres_l, next_groups = [], []
            for g in groups:
                c, lab = kmajority(desc[g], k, rng)
                centres_l.append(c)
                next_groups.extend(g[lab == j] for j in range(k))
            levels.append(np.concatenate(centres_l))
            groups = next_groups
        voc = cls(k, levels, np.zeros(k ** depth))
        words = voc.words(desc)
        n_img = int(n_images.max()) + 1
        pairs = np.unique(np.c_[words, n_images], axis=0)
        df = np.bincount(pairs[:, 0], minlength=voc.n_words)
        voc.idf = np.log(n_img / np.maximum(df, 1)) + np.where(df == 0, 0.0, 0.0)
        voc.idf[df == 0] = np.log(n_img)
        return voc

    def save(self, path: str | Path) -> None:
        np.savez_compressed(path, k=self.k, idf=self.idf, **{f"level{i}": c for i, c in enumerate(self.levels)})

    @classmethod
    def load(cls, path: str | Path | None = None) -> "Vocabulary":
        with np.load(Path(path) if path else DEFAULT_PATH) as z:
            n = len([f for f in z.files if f.startswith("level")])
            return cls(int(z["k"]), [z[f"level{i}"] for i in range(n)], z["idf"])

    # --------------------------------------------------------------- transform
    def words(self, desc: np.ndarray) -> np.ndarray:
        """Word id per descriptor [N,32] -> [N] int64 (greedy descent of the tree)."""
        d64 = np.ascontiguousarray(desc).view(np.uint64)  # [N,4]
        node = np.zeros(len(desc), np.int64)
        for c in self._lv64:
            ch = c[node]  # [N,k,4]
            dist = np.bitwise_count(ch ^ d64[:, None, :]).sum(-1)
            node = node * self.k + dist.argmin(1)
        return node

    def bow(self, words: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """tf-idf vector of a word list -> (sorted word ids [W], L1-normalised weights [W])."""
        if len(words) == 0:
            return np.zeros(0, np.int64), np.zeros(0)
        w, cnt = np.unique(words, return_counts=True)
        val = cnt / len(words) * self.idf[w]
        s = val.sum()
        return w, (val / s if s > 0 else val)


def bow_score(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> float:
    """DBoW2 L1 score in [0,1] of two bow vectors (word ids, weights)."""
    _, ia, ib = np.intersect1d(a[0], b[0], assume_unique=True, return_indices=True)
    if len(ia) == 0:
        return 0.0
    va, vb = a[1][ia], b[1][ib]
    return float(0.5 * (np.abs(va) + np.abs(vb) - np.abs(va - vb)).sum())


class KeyFrameDatabase:
    """Inverted index word -> keyframes, for loop and relocalization candidates."""

    def __init__(self) -> None:
        self.index: dict[int, set[int]] = {}
        self.bows: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def add(self, kf_id: int, bow: tuple[np.ndarray, np.ndarray]) -> None:
        self.bows[kf_id] = bow
        for w in bow[0].tolist():
            self.index.setdefault(w, set()).add(kf_id)

    def erase(self, kf_id: int) -> None:
        bow = self.bows.pop(kf_id, None)
        if bow is not None:
            for w in bow[0].tolist():
                self.index.get(w, set()).discard(kf_id)

    def common_words(self, bow: tuple[np.ndarray, np.ndarray], exclude: set[int]) -> dict[int, int]:
        counts: dict[int, int] = {}
        for w in bow[0].tolist():
            for k in self.index.get(w, ()):
                if k not in exclude:
                    counts[k] = counts.get(k, 0) + 1
        return counts

    def candidates(self, bow: tuple[np.ndarray, np.ndarray], exclude: set[int], min_score: float,
                   covisible: dict[int, list[int]], max_out: int = 10) -> list[int]:
        """DBoW2/ORB-SLAM candidate selection: keyframes sharing >= 80 % of the best word count,
        scored, then accumulated over their 10 best covisible keyframes; best groups win."""
        counts = self.common_words(bow, exclude)
        if not counts:
            return []
        min_common = 0.8 * max(counts.values())
        scored = {k: bow_score(bow, self.bows[k]) for k, c in counts.items() if c > min_common}
        scored = {k: s for k, s in scored.items() if s >= min_score}
        if not scored:
            return []
        acc = []
        for k, s in scored.items():
            total, best_k, best_s = s, k, s
            for n in covisible.get(k, [])[:10]:
                if n in scored:
                    total += scored[n]
                    if scored[n] > best_s:
                        best_k, best_s = n, scored[n]
            acc.append((total, best_k))
        best_total = max(a for a, _ in acc)
        out = []
        for total, k in sorted(acc, key=lambda t: (-t[0], t[1])):
            if total > 0.75 * best_total and k not in out:
                out.append(k)
        return out[:max_out]


def train_from_images(paths: list[str], n_features: int = 1500, k: int = 8, depth: int = 4,
                      fast_threshold: int = 7) -> Vocabulary:
    """Vocabulary from the ORB features of images (files read with OpenCV, grey)."""
    import cv2

    from segs.slam.features import OrbExtractor

    ex = OrbExtractor(n_features, 1.2, 8, fast_threshold, min(fast_threshold, 5))
    descs, owner = [], []
    for i, p in enumerate(paths):
        img = cv2.imread(p, cv2.IMREAD_GRAYSCALE)
        if img is None:
            continue
        kp = ex.extract(img)
        descs.append(kp.desc)
        owner.append(np.full(len(kp), i))
    return Vocabulary.train(np.concatenate(descs), np.concatenate(owner), k, depth)


def main() -> None:
    ap = argparse.ArgumentParser(description="Train an ORB vocabulary tree from images.")
    ap.add_argument("images", nargs="+", help="image files")
    ap.add_argument("--out", default=str(DEFAULT_PATH))
    ap.add_argument("-k", type=int, default=8)
    ap.add_argument("--depth", type=int, default=4)
    a = ap.parse_args()
    voc = train_from_images(sorted(a.images), k=a.k, depth=a.depth)
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    voc.save(a.out)
    print(f"vocabulary: {voc.n_words} words -> {a.out}")


if __name__ == "__main__":
    main()
