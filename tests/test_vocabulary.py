"""BoW vocabulary: the shipped tree, training (augmented views, reproducible), loading errors, the
database query, the training corpus and its command line."""
from __future__ import annotations

import importlib.util

import cv2
import numpy as np
import pytest

from segs.data.synthetic import SyntheticSequence
from segs.errors import ConfigError, DataError
from segs.slam.config import group_from_yaml
from segs.slam.features.extractor import OrbExtractor, to_gray
from segs.slam.map import vocabulary as V
from segs.slam.map.vocabulary import KeyFrameDatabase, TrainingConfig, Vocabulary, bow_score

SMALL = TrainingConfig(k=4, depth=2, views=3, features=group_from_yaml("features", n_features=300))


@pytest.fixture(scope="module")
def images(tmp_path_factory):
    """Two 320x240 grey renders of the procedural room (seed 99, no test of the frontend uses it)."""
    seq = SyntheticSequence(sensor="mono", n_frames=30, width=320, height=240, seed=99)
    folder = tmp_path_factory.mktemp("imgs")
    paths = []
    for i in (0, 15):
        paths.append(folder / f"{i}.png")
        cv2.imwrite(str(paths[-1]), to_gray(seq[i].rgb))
    return paths


def test_shipped_vocabulary_is_the_default_and_small():
    voc = Vocabulary.load()
    assert V.DEFAULT_PATH.name == "orb_k10_l4.npz" and V.DEFAULT_PATH.stat().st_size < 1_000_000
    assert (voc.k, len(voc.levels), voc.n_words) == (10, 4, 10_000)
    assert np.isfinite(voc.idf).all() and voc.idf.min() >= 0 and voc.idf.max() > 0
    # the old tree trained on the bundled test frames is gone
    assert list(V.DEFAULT_PATH.parent.glob("*.npz")) == [V.DEFAULT_PATH]


def test_training_is_reproducible_and_survives_save_load(images, tmp_path):
    voc, n_desc, n_views = V.train_from_images(images, SMALL)
    again, _, _ = V.train_from_images(images, SMALL)
    assert n_views == 2 * SMALL.views and n_desc > 2 * SMALL.features.n_features
    assert voc.n_words == 16 and all(np.array_equal(a, b) for a, b in zip(voc.levels, again.levels))
    assert np.array_equal(voc.idf, again.idf)
    other, _, _ = V.train_from_images(images, TrainingConfig(k=4, depth=2, views=3, seed=1, features=SMALL.features))
    assert not all(np.array_equal(a, b) for a, b in zip(voc.levels, other.levels))
    voc.save(tmp_path / "v.npz")
    loaded = Vocabulary.load(tmp_path / "v.npz")
    desc = OrbExtractor(300).extract(cv2.imread(str(images[0]), cv2.IMREAD_GRAYSCALE)).desc
    assert np.array_equal(loaded.words(desc), voc.words(desc))
    assert not list(tmp_path.glob("*.tmp"))


def test_augmented_views_stay_in_bounds_and_drop_border_descriptors(images):
    img = cv2.imread(str(images[0]), cv2.IMREAD_GRAYSCALE)
    rng = np.random.default_rng(0)
    ex = OrbExtractor(500)
    for _ in range(5):
        view, valid = V.augment(img, rng, (200, 150))
        assert view.dtype == np.uint8 and valid.dtype == bool and view.shape == valid.shape
        assert view.shape[0] <= 150 and view.shape[1] <= 200 and valid.any()
        assert (view[~valid] == 0).all()
    # a view whose right half is outside the image: no descriptor of the black border edge
    half = img.copy()
    half[:, 160:] = 0
    valid = np.zeros(img.shape, bool)
    valid[:, :160] = True
    kept = V.view_descriptors(ex, half, valid)
    kp = ex.extract(half)
    near_edge = (kp.uv[:, 0] > 160 - 22 * ex.scales[kp.octave]).sum()
    assert near_edge > 0 and len(kept) <= len(kp) - near_edge


def test_database_query_ranks_the_same_view_first(images):
    voc = Vocabulary.load()
    ex = OrbExtractor(500)
    seq = SyntheticSequence(sensor="mono", n_frames=30, width=320, height=240, seed=99)
    bows = {i: voc.bow(voc.words(ex.extract(to_gray(seq[i].rgb)).desc)) for i in (0, 1, 10, 20)}
    db = KeyFrameDatabase()
    for i in (0, 10, 20):
        db.add(i, bows[i])
    res = db.query(bows[0], n=3)
    assert res[0] == (0, pytest.approx(1.0)) and len(res) == 3
    assert [s for _, s in res] == sorted((s for _, s in res), reverse=True)
    assert db.query(bows[1], n=1)[0][0] == 0  # the neighbouring frame finds its place
    assert 0 not in [k for k, _ in db.query(bows[0], exclude={0})]
    assert res[1][1] == pytest.approx(bow_score(bows[0], bows[res[1][0]]))
    for ex in (set(), {10}, {0, 10, 20}):  # the C++ count through the inverted index, in the same order
        got = db.common_words(bows[1], ex, native=True)
        assert list(got.items()) == list(db.common_words(bows[1], ex, native=False).items())
        assert set(got) == {0, 10, 20} - ex and all(c > 0 for c in got.values())
    db.erase(0)
    assert 0 not in [k for k, _ in db.query(bows[0])]


def test_load_reports_a_missing_or_malformed_file(tmp_path):
    with pytest.raises(ConfigError, match="slam.loop.vocabulary: .*nope.npz: file not found"):
        Vocabulary.load(tmp_path / "nope.npz")
    (tmp_path / "text.npz").write_text("not a zip")
    with pytest.raises(ConfigError, match="not a vocabulary"):
        Vocabulary.load(tmp_path / "text.npz")
    np.savez(tmp_path / "bad.npz", k=4, idf=np.zeros(16), level0=np.zeros((4, 32), np.uint8),
             level1=np.zeros((15, 32), np.uint8))
    with pytest.raises(ConfigError, match="inconsistent tree"):
        Vocabulary.load(tmp_path / "bad.npz")


def test_corpus_needs_its_packages(monkeypatch):
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: None)
    with pytest.raises(DataError, match=r"need scikit-image .*pip install"):
        V.corpus_paths()


@pytest.mark.skipif(any(importlib.util.find_spec(p) is None for p in ("skimage", "sklearn")),
                    reason="the training corpus needs the 'vocab' extra (scikit-image, scikit-learn)")
def test_corpus_files_are_the_pinned_ones():
    paths = V.corpus_paths()  # raises on a hash mismatch
    assert len(paths) == len(V.CORPUS) == 14
    assert all(cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) is not None for p in paths)


def test_cli_trains_and_reports_bad_input_in_one_line(images, tmp_path, capsys):
    out = tmp_path / "v.npz"
    V.main([str(p) for p in images] + ["--out", str(out), "-k", "4", "--depth", "2", "--views", "2"])
    assert "16 words" in capsys.readouterr().out and Vocabulary.load(out).n_words == 16
    for args in (["missing.png"], [str(images[0]), "-k", "1"]):
        with pytest.raises(SystemExit) as e:
            V.main(args + ["--out", str(tmp_path / "never.npz")])
        err = capsys.readouterr().err
        assert e.value.code == 2 and err.startswith("error: ") and err.count("\n") == 1
    assert not (tmp_path / "never.npz").exists()


def test_native_words_equal_the_numpy_descent(images):
    """The C++ tree descent gives numpy's words, ties included (random descriptors tie often)."""
    from segs.slam.native import kernels

    if kernels() is None:
        pytest.skip("the C++ SLAM kernel cannot be built here (no compiler)")
    voc = Vocabulary.load()
    real = OrbExtractor(500).extract(cv2.imread(str(images[0]), cv2.IMREAD_GRAYSCALE)).desc
    rand = np.random.default_rng(0).integers(0, 256, (2000, 32), dtype=np.uint8)
    for desc in (real, rand, rand[:0]):
        assert np.array_equal(voc.words(desc, native=True), voc.words(desc, native=False))
