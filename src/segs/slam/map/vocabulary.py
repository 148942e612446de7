"""Bag of binary words (DBoW2's idea) for place recognition: relocalization and loop detection.

A vocabulary tree of branching k and depth L is trained by hierarchical k-majority clustering of
ORB descriptors (k-means for Hamming space: centres are bitwise majority votes). Words are the
leaves; tf-idf weights, L1-normalised vectors and DBoW2's L1 score s = 1 - |v1 - v2|_1 / 2.

The shipped vocabulary (``vocab/orb_k10_l4.npz``, k = 10, L = 4: 10,000 words) is trained on
none of the test data: `CORPUS` lists 14 photographs bundled in the scikit-image and scikit-learn
wheels (public domain, CC0 or CC BY 2.0; checked by SHA-256), each seen as
``TrainingConfig.views`` random views (`augment`: perspective tilt, rotation, scale, crop to at
most 640x480, gain / gamma / blur / noise / JPEG). Reproduce it (seed fixed) with::

    pip install -e ".[vocab]"          # scikit-image and scikit-learn, for their images only
    python -m segs.slam.map.vocabulary # -> src/segs/slam/map/vocab/orb_k10_l4.npz

``python -m segs.slam.map.vocabulary IMG... --out my.npz`` trains on your own images instead
(``loop.vocabulary: my.npz`` uses it). docs/data.md ("BoW vocabulary") has the image list,
licences and the place-recognition recall on 7-Scenes frames.
"""
from __future__ import annotations

import argparse
import hashlib
import importlib.util
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from segs import process_settings
from segs.errors import ConfigError, DataError, UserInputError
from segs.slam.config import FeatureConfig, group_from_yaml
from segs.slam.features.extractor import hamming_matrix
from segs.slam.native import kernels

DEFAULT_PATH = Path(__file__).with_name("vocab") / "orb_k10_l4.npz"

# Training photographs bundled in PyPI wheels (no download), none from the test data, each with
# the licence its package states: (package, file inside the package, SHA-256 prefix, licence)
CORPUS = (
    ("skimage", "data/astronaut.png", "88431cd9653ccd53", "public domain (NASA)"),
    ("skimage", "data/camera.png", "b0793d2adda0fa6a", "CC0 (Lav Varshney)"),
    ("skimage", "data/chelsea.png", "596aa1e7cb875eb7", "CC0 (Stefan van der Walt)"),
    ("skimage", "data/coffee.png", "cc02f8ca188b167c", "CC0 (Rachel Michetti)"),
    ("skimage", "data/rocket.jpg", "c2dd0de7c538df8d", "public domain (SpaceX)"),
    ("skimage", "data/coins.png", "f8d773fc9cfa6f4d", "no known copyright restrictions (Brooklyn Museum)"),
    ("skimage", "data/clock_motion.png", "f029226b28b642e8", "public domain (Stefan van der Walt)"),
    ("skimage", "data/brick.png", "7966caf324f6ba84", "CC0 (CC0Textures)"),
    ("skimage", "data/grass.png", "b6b6022426b38936", "CC0 (DeviantArt, linolafett)"),
    ("skimage", "data/gravel.png", "c48615b451bf1e60", "CC0 (CC0Textures)"),
    ("skimage", "data/text.png", "bd84aa3a6e3c9887", "public domain (Wikipedia)"),
    ("skimage", "data/hubble_deep_field.jpg", "3a19c5dd8a927a93", "public domain (NASA)"),
    ("sklearn", "datasets/images/china.jpg", "8378025ad2519d64", "CC BY 2.0 (danielbuechele, Flickr)"),
    ("sklearn", "datasets/images/flower.jpg", "a77f6ec41e353afd", "CC BY 2.0 (vultilion, Flickr)"),
)
_PIP_NAMES = {"skimage": "scikit-image", "sklearn": "scikit-learn"}


@dataclass
class TrainingConfig:
    """Vocabulary training: tree shape, views per image and the ORB settings.

    k, depth: branching and levels (k^depth words); views: per image, the image itself and
    views - 1 random augmentations (`augment`); max_size: (width, height) of a view at most;
    seed: the augmentations and the clustering; features: the extractor's (the frontend's:
    segs.slam.config.group_from_yaml("features")). The others' defaults are this program's
    (python -m segs.slam.map.vocabulary), which no config composes."""

    features: FeatureConfig
    k: int = 10
    depth: int = 4
    views: int = 32
    seed: int = 0
    max_size: tuple[int, int] = (640, 480)


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
    def train(cls, desc: np.ndarray, n_images: np.ndarray, k: int = TrainingConfig.k,
              depth: int = TrainingConfig.depth, seed: int = TrainingConfig.seed) -> "Vocabulary":
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
        voc.idf = np.log(n_img / np.maximum(df, 1))  # a word no image has weighs like the rarest
        return voc

    def save(self, path: str | Path) -> None:
        """Write the tree (.npz; idf as float32), through a temporary file: never half written."""
        path = Path(path)
        tmp = path.with_name(path.name + ".tmp")
        with open(tmp, "wb") as f:
            np.savez_compressed(f, k=self.k, idf=self.idf.astype(np.float32),
                                **{f"level{i}": c for i, c in enumerate(self.levels)})
        os.replace(tmp, path)

    @classmethod
    def load(cls, path: str | Path | None = None) -> "Vocabulary":
        """A saved tree (.npz); None = the shipped one. Missing or malformed: ConfigError."""
        path = Path(path) if path else DEFAULT_PATH
        if not path.is_file():
            raise ConfigError(f"slam.loop.vocabulary: {path}: file not found")
        try:
            with np.load(path) as z:
                n = len([f for f in z.files if f.startswith("level")])
                k, levels, idf = int(z["k"]), [z[f"level{i}"] for i in range(n)], z["idf"]
        except (OSError, ValueError, KeyError) as e:
            raise ConfigError(f"slam.loop.vocabulary: {path}: not a vocabulary .npz ({type(e).__name__})") from None
        shapes_ok = n > 0 and all(c.shape == (k ** (i + 1), 32) and c.dtype == np.uint8 for i, c in enumerate(levels))
        if not shapes_ok or idf.shape != (k ** n,):
            raise ConfigError(f"slam.loop.vocabulary: {path}: inconsistent tree (k={k}, {n} levels)")
        return cls(k, levels, idf)

    # --------------------------------------------------------------- transform
    def words(self, desc: np.ndarray, native: bool = True) -> np.ndarray:
        """Word id per descriptor [N,32] -> [N] int64 (greedy descent of the tree; the C++ loop
        where built)."""
        ext = kernels() if native else None
        if ext is not None:
            return ext.tree_words(np.ascontiguousarray(desc, np.uint8).reshape(-1, 32), self.levels, self.k)
        d64 = np.ascontiguousarray(desc).view(np.uint64)  # [N,4]
        node = np.zeros(len(desc), np.int64)
        for c in self._lv64:
            ch = c[node]  # [N,k,4]
            dist = np.bitwise_count(ch ^ d64[:, None, :]).sum(-1)
            node = node * self.k + dist.argmin(1)
        return node

    def nodes(self, words: np.ndarray, level: int) -> np.ndarray:
        """Ancestor node id [N] of words [N] at tree level `level` (1: the root's k children)."""
        return np.asarray(words, np.int64) // self.k ** (len(self.levels) - int(level))

    def bow(self, words: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """tf-idf vector of a word list -> (sorted word ids [W], L1-normalised weights [W])."""
        if len(words) == 0:
            return np.zeros(0, np.int64), np.zeros(0)
        w, cnt = np.unique(words, return_counts=True)
        val = cnt / len(words) * self.idf[w]
        s = val.sum()
        return w, (val / s if s > 0 else val)

    def bow_of(self, desc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Bag of words of descriptors [N,32] (`bow(words(desc))`)."""
        return self.bow(self.words(desc))


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

    def clear(self) -> None:
        """Forget every keyframe (a rejected monocular initial map)."""
        self.index = {}
        self.bows = {}

    def erase(self, kf_id: int) -> None:
        bow = self.bows.pop(kf_id, None)
        if bow is not None:
            for w in bow[0].tolist():
                self.index.get(w, set()).discard(kf_id)

    def common_words(self, bow: tuple[np.ndarray, np.ndarray], exclude: set[int],
                     native: bool = True) -> dict[int, int]:
        """Keyframe id (not in exclude) -> how many of bow's words it has, first-seen order (the C++
        loop where built)."""
        ext = kernels() if native else None
        if ext is not None:
            keys, cnt = ext.common_words(np.ascontiguousarray(bow[0], np.int64), self.index,
                                         exclude if isinstance(exclude, (set, frozenset)) else set(exclude))
            return dict(zip(keys.tolist(), cnt.tolist()))
        counts: dict[int, int] = {}
        for w in bow[0].tolist():
            for k in self.index.get(w, ()):
                if k not in exclude:
                    counts[k] = counts.get(k, 0) + 1
        return counts

    def query(self, bow: tuple[np.ndarray, np.ndarray], n: int = 10,
              exclude: set[int] = frozenset()) -> list[tuple[int, float]]:
        """DBoW2's database query: the n keyframes of best score with bow (sharing a word, not in
        exclude) -> [(kf_id, score)], best first (ties by id)."""
        scored = [(k, bow_score(bow, self.bows[k])) for k in self.common_words(bow, exclude)]
        return sorted(scored, key=lambda t: (-t[1], t[0]))[:n]

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



# ------------------------------------------------------------------- training corpus
def corpus_paths() -> list[Path]:
    """The files of `CORPUS` in the installed packages (located, not imported; hashes checked)."""
    out = []
    for pkg, rel, sha, _ in CORPUS:
        spec = importlib.util.find_spec(pkg)
        if spec is None or not spec.submodule_search_locations:
            raise DataError(f"vocabulary: the training images need {_PIP_NAMES[pkg]} "
                            "(pip install -e '.[vocab]')")
        path = Path(list(spec.submodule_search_locations)[0]) / rel
        if not path.is_file():
            raise DataError(f"{path}: training image not found in the installed {_PIP_NAMES[pkg]}")
        digest = hashlib.sha256(path.read_bytes()).hexdigest()
        if not digest.startswith(sha):
            raise DataError(f"{path}: SHA-256 {digest[:16]}, expected {sha} (another version of the image)")
        out.append(path)
    return out


def _view_homography(h: int, w: int, rng: np.random.Generator,
                     max_size: tuple[int, int]) -> tuple[np.ndarray, tuple[int, int]]:
    """Random homography [3,3] from an h x w image to a view, and the view size (width, height).

    A virtual camera (focal max(h, w), looking at the image centre) turns by up to 35 degrees
    about a random axis in the image plane (perspective), then rotation +-30 degrees and scale
    0.5-2 (log-uniform); the view is a random crop of the result of at most max_size."""
    import cv2

    f = float(max(h, w))
    cam = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]])
    a = rng.uniform(0, 2 * np.pi)
    turn = cv2.Rodrigues(np.radians(rng.uniform(0, 35)) * np.array([np.cos(a), np.sin(a), 0.0]))[0]
    sim = np.eye(3)
    angle = rng.uniform(-30, 30)
    sim[:2] = cv2.getRotationMatrix2D((0.0, 0.0), angle, float(np.exp(rng.uniform(np.log(0.5), np.log(2)))))
    H = sim @ cam @ turn @ np.linalg.inv(cam)
    corners = np.array([[0, 0], [w, 0], [w, h], [0, h]], np.float64).reshape(-1, 1, 2)
    warped = cv2.perspectiveTransform(corners, H).reshape(-1, 2)
    lo, hi = warped.min(0), warped.max(0)
    size = np.minimum(np.ceil(hi - lo), max_size).astype(int)
    origin = lo + rng.uniform(0, 1, 2) * np.maximum(hi - lo - size, 0)
    shift = np.array([[1, 0, -origin[0]], [0, 1, -origin[1]], [0, 0, 1]])
    return shift @ H, (int(size[0]), int(size[1]))


def augment(gray: np.ndarray, rng: np.random.Generator,
            max_size: tuple[int, int] = TrainingConfig.max_size) -> tuple[np.ndarray, np.ndarray]:
    """A random view of a grey image [H,W] uint8 -> (view [h,w] uint8, valid [h,w] bool: inside
    the source image). Geometry: `_view_homography`; photometry: gamma 0.6-1.6, gain 0.6-1.3,
    offset +-0.1, Gaussian blur (sigma 0.3-1.2, half the views), noise (sigma <= 3 grey levels),
    JPEG re-encoding at quality 50-95 (70 % of the views)."""
    import cv2

    H, (w, h) = _view_homography(*gray.shape, rng, max_size)
    view = cv2.warpPerspective(gray, H, (w, h), flags=cv2.INTER_LINEAR, borderValue=0)
    inside = cv2.warpPerspective(np.full_like(gray, 255), H, (w, h), flags=cv2.INTER_NEAREST, borderValue=0)
    valid = inside > 0
    x = (view.astype(np.float32) / 255.0) ** float(np.exp(rng.uniform(np.log(0.6), np.log(1.6))))
    x = x * rng.uniform(0.6, 1.3) + rng.uniform(-0.1, 0.1)
    if rng.random() < 0.5:
        x = cv2.GaussianBlur(x, (0, 0), rng.uniform(0.3, 1.2))
    x = x + rng.normal(0.0, rng.uniform(0, 3 / 255), x.shape).astype(np.float32)
    view = np.clip(x * 255.0 + 0.5, 0, 255).astype(np.uint8)
    if rng.random() < 0.7:
        _, buf = cv2.imencode(".jpg", view, [cv2.IMWRITE_JPEG_QUALITY, int(rng.integers(50, 96))])
        view = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
    view[~valid] = 0
    return view, valid


def view_descriptors(extractor, view: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """ORB descriptors [N,32] uint8 of a view [h,w] uint8 whose rotated 31-pixel patch lies
    inside valid [h,w] bool (no descriptor of the black border). extractor: an OrbExtractor."""
    import cv2

    kp = extractor.extract(view)
    if len(kp) == 0:
        return kp.desc
    inside = cv2.distanceTransform(valid.astype(np.uint8), cv2.DIST_L2, 3)
    u = np.clip(np.round(kp.uv[:, 0]).astype(int), 0, view.shape[1] - 1)
    v = np.clip(np.round(kp.uv[:, 1]).astype(int), 0, view.shape[0] - 1)
    keep = inside[v, u] > 22.0 * extractor.scales[kp.octave]  # 15 sqrt(2) + margin, level pixels
    return kp.desc[keep]


def training_views(paths: list[str | Path], cfg: TrainingConfig) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """(view [h,w] uint8, valid [h,w] bool) of the training set: cfg.views views of each image
    (read grey with OpenCV; the first is the image itself)."""
    import cv2

    rng = np.random.default_rng(cfg.seed)
    for p in paths:
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise DataError(f"{p}: cannot read image (missing, unreadable or corrupt)")
        yield img, np.ones(img.shape, bool)
        for _ in range(cfg.views - 1):
            yield augment(img, rng, cfg.max_size)


def train_from_images(paths: list[str | Path], cfg: TrainingConfig) -> tuple[Vocabulary, int, int]:
    """Vocabulary from the ORB features of `training_views` (each view is an image of the idf)
    -> (vocabulary, descriptors, views)."""
    from segs.slam.features.extractor import OrbExtractor

    fc = cfg.features
    ex = OrbExtractor.from_config(fc)
    descs, owner = [], []
    for view, valid in training_views(paths, cfg):
        d = view_descriptors(ex, view, valid)
        descs.append(d)
        owner.append(np.full(len(d), len(owner)))
    desc = np.concatenate(descs) if descs else np.zeros((0, 32), np.uint8)
    if len(desc) < cfg.k ** cfg.depth:
        raise DataError(f"vocabulary: {len(desc)} descriptors for {cfg.k ** cfg.depth} words; "
                        "give more images or views")
    return Vocabulary.train(desc, np.concatenate(owner), cfg.k, cfg.depth, cfg.seed), len(desc), len(owner)


def main(argv: list[str] | None = None) -> None:
    d = TrainingConfig(features=group_from_yaml("features"))
    ap = argparse.ArgumentParser(description="Train an ORB vocabulary tree (default: the shipped one, "
                                 "from the bundled corpus of photographs).")
    ap.add_argument("images", nargs="*", help="image files (default: the corpus, needs the 'vocab' extra)")
    ap.add_argument("--out", default=str(DEFAULT_PATH))
    ap.add_argument("-k", type=int, default=d.k, help="branching")
    ap.add_argument("--depth", type=int, default=d.depth, help="levels (k^depth words)")
    ap.add_argument("--views", type=int, default=d.views, help="views per image (1 = the image only)")
    ap.add_argument("--seed", type=int, default=d.seed)
    a = ap.parse_args(argv)
    try:
        if a.k < 2 or a.depth < 1 or a.views < 1:
            raise ConfigError("vocabulary: need -k >= 2, --depth >= 1 and --views >= 1")
        paths = sorted(a.images) if a.images else corpus_paths()
        t0 = time.perf_counter()
        cfg = TrainingConfig(d.features, k=a.k, depth=a.depth, views=a.views, seed=a.seed)
        voc, n_desc, n_views = train_from_images(paths, cfg)
    except UserInputError as e:
        print(f"error: {e}", file=sys.stderr)
        raise SystemExit(2) from None
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    voc.save(a.out)
    print(f"vocabulary: {voc.n_words} words (k={voc.k}, L={len(voc.levels)}) from {len(paths)} images, "
          f"{n_views} views, {n_desc} descriptors in {time.perf_counter() - t0:.0f} s -> {a.out}")


if __name__ == "__main__":
    process_settings.apply()
    main()
