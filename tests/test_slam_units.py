"""Components of the ORB frontend: features, matching grid, native kernels, vocabulary, config, modes,
state (pose refinement, bundle adjustment, pose graph, two-view reconstruction: tests/test_slam_estimation.py)."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from segs.data.synthetic import SyntheticSequence
from segs.errors import ConfigError
from segs.slam import config as C
from segs.slam.features.extractor import OrbExtractor, hamming, hamming_matrix, to_gray
from segs.slam.features.frame import KeypointGrid
from segs.slam.estimation.matching import knn_hamming
from segs.slam.estimation.optimize import BundleAdjuster
from conftest import orb_v2_state, project, se3
from segs.pipeline.sources import run_sequence
from segs.slam.map.vocabulary import Vocabulary, bow_score
from segs.config import slam_frontend

ROOT = Path(__file__).resolve().parents[1]
K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])


@pytest.fixture(scope="module")
def image():
    seq = SyntheticSequence(sensor="mono", n_frames=4, width=320, height=240, seed=0)
    return to_gray(seq[0].rgb), to_gray(seq[1].rgb)



def test_to_gray_rounds_and_saturates():
    """Float RGB in [0,1] -> the grey of round(255 x), values outside [0,1] saturated."""
    rng = np.random.default_rng(0)
    u8 = rng.integers(0, 256, (5, 6, 3), dtype=np.uint8)
    np.testing.assert_array_equal(to_gray(u8.astype(np.float32) / 255.0), cv2.cvtColor(u8, cv2.COLOR_RGB2GRAY))
    np.testing.assert_array_equal(to_gray(u8.astype(np.float64) / 255.0), cv2.cvtColor(u8, cv2.COLOR_RGB2GRAY))
    off = np.zeros((2, 2, 3), np.float32)
    off[0, 0], off[0, 1], off[1, 0] = -0.5, 2.0, (1.0, 0.0, 0.0)
    gray = to_gray(off)
    assert gray[0, 0] == 0 and gray[0, 1] == 255 and gray[1, 0] == cv2.cvtColor(
        np.array([[[255, 0, 0]]], np.uint8), cv2.COLOR_RGB2GRAY)[0, 0]
    np.testing.assert_array_equal(to_gray(u8[:, :, 0].astype(np.float32) / 255.0), u8[:, :, 0])

def test_orb_extractor_counts_and_spreads_keypoints(image):
    ex = OrbExtractor(500, 1.2, 8, 20, 7, cell_size=30)
    kp = ex.extract(image[0])
    assert 0 < len(kp) <= 500
    assert kp.desc.shape == (len(kp), 32) and kp.desc.dtype == np.uint8
    assert kp.octave.min() >= 0 and kp.octave.max() < 8
    plain = cv2.ORB_create(500, 1.2, 8).detect(image[0], None)

    def coverage(uv):  # occupied 40x40 cells of the image
        return len({(int(u // 40), int(v // 40)) for u, v in uv})

    assert coverage(kp.uv) >= coverage([k.pt for k in plain])


def test_orb_extractor_lowers_fast_threshold_only_as_far_as_needed(image):
    """FAST thresholds are tried in turn (20, 7, 3) until one finds n_features corners: a
    low-contrast image gets its keypoints from the third pass, a textured one never reaches it."""
    flat = (128 + 0.1 * (image[0].astype(np.float64) - 128)).round().astype(np.uint8)  # 90 % contrast cut
    two, three = OrbExtractor(500, 1.2, 8, 20, 7, floor_fast_threshold=7), OrbExtractor(500, 1.2, 8, 20, 7)
    assert two.fast_thresholds == (20, 7) and three.fast_thresholds == (20, 7, 3)
    few, many = two.extract(flat), three.extract(flat)
    assert len(few) < 200 and len(many) == 500
    plain = cv2.ORB_create(1500, 1.2, 8, 19, 0, 2, cv2.ORB_HARRIS_SCORE, 31, 3).detect(flat, None)
    assert set(map(tuple, many.uv.round(3))) <= {(round(k.pt[0], 3), round(k.pt[1], 3)) for k in plain}
    rich_two, rich_three = two.extract(image[0]), three.extract(image[0])  # enough corners at 20 or 7
    assert len(rich_two) == 500 and np.array_equal(rich_two.uv, rich_three.uv)
    assert np.array_equal(rich_two.desc, rich_three.desc)


def test_orb_extractor_descriptors_equal_opencvs_over_all_candidates(image):
    """Descriptors computed for the distributed keypoints only are the bytes (and the keypoints
    the ones) that detectAndCompute over every candidate gives for them."""
    ex = OrbExtractor(300, 1.2, 8, 20, 7, oversample=3.0)
    for img in image:
        kp = ex.extract(img)
        kps, desc = cv2.ORB_create(900, 1.2, 8, 19, 0, 2, cv2.ORB_HARRIS_SCORE, 31, 20).detectAndCompute(img, None)
        rows = {(k.pt, k.octave): i for i, k in enumerate(kps)}
        idx = [rows[((float(np.float32(u)), float(np.float32(v))), int(o))] for (u, v), o in zip(kp.uv, kp.octave)]
        assert 0 < len(kp) <= 300 and len(set(idx)) == len(kp)
        np.testing.assert_array_equal(kp.desc, desc[idx])
        np.testing.assert_array_equal(kp.angle, np.float32([kps[i].angle for i in idx]))
        np.testing.assert_array_equal(kp.response, np.float32([kps[i].response for i in idx]))


def test_hamming_matches_opencv(image):
    kp = OrbExtractor(200, 1.2, 8, 20, 7).extract(image[0])
    d = kp.desc
    ref = np.array([[cv2.norm(a, b, cv2.NORM_HAMMING) for b in d[:20]] for a in d[:30]])
    assert np.array_equal(hamming_matrix(d[:30], d[:20]), ref)
    assert np.array_equal(hamming(d[:20], d[:20][::-1]), np.diag(ref[:20, :20][:, ::-1]))


def test_knn_hamming_equals_bfmatcher_knn_including_ties():
    """The C++ kernel and cv2.batchDistance against BFMatcher.knnMatch, ties included."""
    rng = np.random.default_rng(6)
    a = rng.integers(0, 256, (200, 32), dtype=np.uint8)
    b = rng.integers(0, 256, (150, 32), dtype=np.uint8)
    b[:60] = a[:60] ^ (rng.random((60, 32)) < 0.05).astype(np.uint8)  # near duplicates
    b[60:70] = b[50:60]  # exact ties
    a[100:140] = a[100]  # repeated queries: ties at every rank
    for native in (True, False):
        for db, k in ((b, 8), (b[:3], 8), (b, 2), (b, 1)):
            dist, nidx = knn_hamming(a, db, k, native=native)
            ref = cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(a, db, k=k)
            assert dist.shape == nidx.shape == (len(a), min(k, len(db)))
            for i, ms in enumerate(ref):
                assert [m.trainIdx for m in ms] == nidx[i][nidx[i] >= 0].tolist()
                assert [m.distance for m in ms] == dist[i][nidx[i] >= 0].tolist()


def test_knn_by_node_is_knn_within_each_vocabulary_node():
    from segs.slam.estimation.matching import _knn_by_node

    rng = np.random.default_rng(7)
    a = rng.integers(0, 256, (120, 32), dtype=np.uint8)
    b = rng.integers(0, 256, (90, 32), dtype=np.uint8)
    b[:40] = a[:40] ^ (rng.random((40, 32)) < 0.05).astype(np.uint8)
    na, nb = rng.integers(0, 4, 120), rng.integers(0, 5, 90)
    q, t, d = _knn_by_node(a, na, b, nb, 3)
    assert (na[q] == nb[t]).all() and np.all(np.diff(q) >= 0)  # same node, query-major
    for i in range(len(a)):
        cand = np.flatnonzero(nb == na[i])
        dist = hamming_matrix(a[i:i + 1], b[cand])[0]
        want = np.sort(dist)[:3]
        assert np.array_equal(d[q == i], want)  # the 3 nearest of the node, nearest first
    # one node for all: the plain kNN
    q1, t1, d1 = _knn_by_node(a, np.zeros(120, np.int64), b, np.zeros(90, np.int64), 3)
    dist, nidx = knn_hamming(a, b, 3)
    assert np.array_equal(q1, np.repeat(np.arange(120), 3)) and np.array_equal(d1, dist.ravel())


def test_keypoint_grid_query_equals_brute_force():
    rng = np.random.default_rng(0)
    uv = rng.uniform([0, 0], [320, 240], (400, 2))
    q = rng.uniform([-10, -10], [330, 250], (50, 2))
    r = rng.uniform(1, 40, 50)
    qi, ki = KeypointGrid(uv, 320, 240, cell=16).query(q, r)
    got = set(zip(qi.tolist(), ki.tolist()))
    d = np.linalg.norm(q[:, None] - uv[None], axis=2)
    want = set(zip(*np.nonzero(d <= r[:, None])))
    assert got == want


def _grid_frame(rng, n=600, dup_desc=False):
    """A SlamFrame-like record (kp, grid, points, ur) with random keypoints, some taken, some with
    depth; dup_desc: few distinct descriptors, so that distance ties are common."""
    from types import SimpleNamespace

    from segs.slam.features.extractor import Keypoints

    uv = rng.uniform([0, 0], [320, 240], (n, 2))
    pool = rng.integers(0, 256, (12 if dup_desc else n, 32), dtype=np.uint8)
    desc = np.ascontiguousarray(pool[rng.integers(0, len(pool), n)])
    kp = Keypoints(uv, rng.integers(0, 8, n), rng.uniform(0, 360, n).astype(np.float32),
                   np.ones(n, np.float32), desc)
    points = np.where(rng.random(n) < 0.2, rng.integers(0, 50, n), -1)
    ur = np.where(rng.random(n) < 0.6, uv[:, 0] - rng.uniform(1, 30, n), -1.0)
    return SimpleNamespace(kp=kp, grid=KeypointGrid(uv, 320, 240, cell=16), points=points, ur=ur)


@pytest.mark.parametrize("dup_desc", [False, True])
@pytest.mark.parametrize("stereo", [False, True])
def test_native_projection_search_equals_numpy(dup_desc, stereo):
    """The C++ kernel (segs.slam.native) returns what the numpy pipeline returns, ties included,
    with queries on cell borders and outside the image."""
    from segs.slam.estimation.matching import nearest_two_in_radius
    from segs.slam.native import kernels

    if kernels() is None:
        pytest.skip("the C++ SLAM kernel cannot be built here (no compiler)")
    rng = np.random.default_rng(3 + dup_desc + 2 * stereo)
    fr = _grid_frame(rng, dup_desc=dup_desc)
    m = 400
    uv = rng.uniform([-20, -20], [340, 260], (m, 2))
    uv[:40] = np.round(uv[:40] / 16) * 16  # exactly on cell borders
    desc = np.ascontiguousarray(fr.kp.desc[rng.integers(0, len(fr.kp), m)] ^ (rng.random((m, 32)) < 0.05).astype(np.uint8))
    radius = rng.uniform(0, 48, m)
    radius[:40] = 16.0
    lvl = rng.integers(0, 8, m)
    ur = uv[:, 0] - rng.uniform(1, 30, m) if stereo else None
    sigma2 = 1.2 ** (2 * np.arange(8))
    gates = [None, (rng.uniform(0.5, 4, m), sigma2, None, 40.0), (rng.uniform(0.5, 4, m), sigma2, 0.8, 40.0)]
    for only_free, gate in ((True, None), (False, None), (False, gates[1]), (True, gates[2])):
        a = nearest_two_in_radius(fr, uv, desc, radius, lvl - 1, lvl + 1, ur, only_free, gate, native=True)
        b = nearest_two_in_radius(fr, uv, desc, radius, lvl - 1, lvl + 1, ur, only_free, gate, native=False)
        assert len(a[0]) > (5 if gate else 100)
        for x, y in zip(a, b):
            assert np.array_equal(x, y)
        if dup_desc and gate is None:  # ties were there to be broken
            assert (a[2] == a[3]).sum() > 10


@pytest.mark.parametrize("stereo", [False, True])
def test_native_pose_solver_equals_numpy(stereo):
    from segs.slam.native import kernels
    from segs.slam.estimation.optimize import _solve_pose

    if kernels() is None:
        pytest.skip("the C++ SLAM kernel cannot be built here (no compiler)")
    rng = np.random.default_rng(4)
    P = rng.uniform([-2, -1.5, 2], [2, 1.5, 6], (150, 3))
    gt = se3([0.05, -0.1, 0.02], [0.1, -0.05, 0.2])
    uv, z = project(K, gt, P)
    uv += rng.normal(0, 1.0, uv.shape)
    ur = np.where(rng.random(150) < 0.7, uv[:, 0] - 30.0 / z, -1.0) if stereo else None
    w = rng.uniform(0.4, 1.0, 150)
    args = (P, uv, ur, w, K, 30.0, ur >= 0 if stereo else None, w * 0.8)
    start = se3([0.07, -0.06, 0.0], [0.16, -0.02, 0.12])
    a = _solve_pose(start, args, 20, native=True)
    b = _solve_pose(start, args, 20, native=False)
    assert np.abs(a - b).max() < 1e-9
    assert np.abs(a - start).max() > 1e-3  # it moved


@pytest.mark.parametrize("ur_sigma", [None, 0.8])
@pytest.mark.parametrize("stereo,warm", [(False, False), (True, False), (True, True)])
def test_native_pose_refinement_equals_numpy(stereo, warm, ur_sigma):
    """ORB-SLAM's PoseOptimization in one C++ call: same pose (to rounding) and same inliers as
    the Python rounds, with outliers to classify, monocular / stereo / RGB-D (ur_sigma)."""
    from segs.slam.native import kernels
    from segs.slam.estimation.optimize import refine_pose

    if kernels() is None:
        pytest.skip("the C++ SLAM kernel cannot be built here (no compiler)")
    rng = np.random.default_rng(7)
    n = 300
    P = rng.uniform([-2, -1.5, 2], [2, 1.5, 6], (n, 3))
    gt = se3([0.03, -0.08, 0.02], [0.1, -0.05, 0.2])
    uv, z = project(K, gt, P)
    octave = rng.integers(0, 8, n)
    uv += rng.normal(0, 1.0, uv.shape) * 1.2 ** octave[:, None]
    uv[:30] += rng.uniform(-40, 40, (30, 2))  # outliers
    ur = np.where(rng.random(n) < 0.7, uv[:, 0] - 40.0 / z + rng.normal(0, 0.5, n), -1.0) if stereo else None
    inv_sigma2 = 1.2 ** (-2.0 * octave)
    start = se3([0.05, -0.06, 0.0], [0.14, -0.02, 0.15])
    kw = dict(rounds=4, min_inliers=10, iterations=20, ur_sigma=ur_sigma if stereo else None, warm=warm)
    a, inl_a = refine_pose(start, P, uv, ur, inv_sigma2, K, 40.0, native=True, **kw)
    b, inl_b = refine_pose(start, P, uv, ur, inv_sigma2, K, 40.0, native=False, **kw)
    assert np.abs(a - b).max() < 1e-9 and np.array_equal(inl_a, inl_b)
    assert inl_a[30:].mean() > 0.9 and inl_a[:30].mean() < 0.5  # it found the outliers
    assert np.abs(a[:3, 3] - gt[:3, 3]).max() < 0.02
    np.testing.assert_allclose(a[:3, :3] @ a[:3, :3].T, np.eye(3), atol=1e-12)
    few, inl_few = refine_pose(start, P[:5], uv[:5], None, inv_sigma2[:5], K, 40.0, native=True, **kw)
    assert np.array_equal(few, start) and not inl_few.any()


def test_native_build_reports_a_missing_compiler(tmp_path, monkeypatch):
    from segs.slam import native

    monkeypatch.setenv("CXX", "no-such-compiler-xyz")
    with pytest.raises(RuntimeError, match="no C\\+\\+ compiler.*no-such-compiler-xyz"):
        native._compile("segs_slam_native_test", tmp_path / "x.so")
    assert not list(tmp_path.iterdir())  # nothing half-written


def test_native_map_bookkeeping_equals_python():
    """Keyframe culling's redundancy count and the point-geometry gather give the Python loops'
    results on a real map (synthetic monocular orbit: many observers per point), including after
    a keyframe is removed."""
    from segs.slam.backend.local_mapping import redundant_points
    from segs.slam.native import kernels

    if kernels() is None:
        pytest.skip("the C++ SLAM kernel cannot be built here (no compiler)")
    seq = SyntheticSequence(sensor="mono", n_frames=40, width=320, height=240, trajectory="orbit", speed=0.3, seed=0)
    fe = slam_frontend(seq.camera, "mono")
    run_sequence(fe, seq)
    m = fe.map
    kfs = sorted(m.kfs)
    assert len(kfs) >= 5
    m.set_kf_bad(m.kfs[kfs[2]])  # observations of a removed keyframe must not count
    octaves = {k: kf.kp.octave for k, kf in m.kfs.items()}
    counted = 0
    for k in sorted(m.kfs)[1:]:
        idx, pids = m.kf_point_ids(m.kfs[k])
        lvl = m.kfs[k].kp.octave[idx] + 1
        for th in (1, 2, 3):
            a = redundant_points(m.obs, pids, lvl, k, octaves, th, native=True)
            assert a == redundant_points(m.obs, pids, lvl, k, octaves, th, native=False)
            counted += a
    assert counted > 0
    pids = np.flatnonzero(m.valid)
    m.ref_kf[pids[::7]] = kfs[2]  # points whose reference keyframe is gone
    for x, y in zip(m.observers(pids, native=True), m.observers(pids, native=False)):
        assert np.array_equal(x, y)
    assert (m.observers(pids)[2] == -1).sum() >= len(pids[::7])
    for k in list(m.kfs)[:4]:
        lacks = m.unobserved_by(pids, k, native=True)
        assert np.array_equal(lacks, m.unobserved_by(pids, k, native=False))
        assert np.array_equal(~lacks, np.isin(pids, m.kfs[k].points)) and 0 < lacks.sum() < len(pids)
        for ex in (k, -1):
            shared = m.count_observers(m.kf_point_ids(m.kfs[k])[1], ex, native=True)
            want = m.count_observers(m.kf_point_ids(m.kfs[k])[1], ex, native=False)
            assert list(shared.items()) == list(want.items()) and shared and (k in shared) == (ex == -1)
    before = m.desc.copy()
    m.update_descriptors(pids, native=False)
    want = m.desc.copy()
    m.desc[:] = before
    m.update_descriptors(pids, native=True)
    assert np.array_equal(m.desc, want) and not np.array_equal(want[pids], before[pids])
    # a keyframe observing points: added, already there, or a second keypoint of the same point
    import copy

    kf = m.kfs[kfs[-1]]
    own = np.flatnonzero(kf.points >= 0)
    other = np.array([p for p in pids.tolist() if kf.kf_id not in m.obs[p]][:30], np.int64)
    free = np.flatnonzero(kf.points < 0)[: len(other) + 2]
    idx = np.concatenate([own[:20], free[: len(other)], free[-2:]])
    pts = np.concatenate([kf.points[own[:20]], other, other[:2]])  # the last two: points just added
    saved = (copy.deepcopy(m.obs), m.n_obs.copy(), kf.points.copy(), m.version)
    results = []
    for native in (True, False):
        m.obs, m.n_obs, kf.points, m.version = copy.deepcopy(saved[0]), saved[1].copy(), saved[2].copy(), saved[3]
        m.observe(kf, idx, pts, native=native)
        results.append((m.obs, m.n_obs.copy(), kf.points.copy(), m.version))
    (o1, n1, k1, v1), (o2, n2, k2, v2) = results
    assert o1 == o2 and np.array_equal(n1, n2) and np.array_equal(k1, k2) and v1 == v2 > saved[3]
    assert (k1[free[-2:]] == -1).all() and np.array_equal(k1[free[: len(other)]], other)
    assert all(o1[p][kf.kf_id] == i for p, i in zip(other.tolist(), free.tolist()))
    # the kernels index the map's own list by point id: an id outside it is an error, not a read
    for bad in (np.array([len(m.obs)]), np.array([-1])):
        with pytest.raises(IndexError):
            kernels().unobserved_by(m.obs, bad, kfs[0])
    with pytest.raises(ValueError, match="octaves"):  # a keyframe's octaves that are not a 1-D array
        kernels().gather_observers(m.obs, pids[:5], {k: np.zeros((2, 2), np.int64) for k in m.kfs}, m.ref_kf[pids[:5]])
    # replaced points: followed to the survivor, or -1 when it is gone too
    chain = pids[:2]
    assert m.live_ids(chain).tolist() == chain.tolist()
    m.replace_point(int(chain[0]), int(chain[1]))
    assert m.live_ids(chain).tolist() == [chain[1]] * 2
    m.set_point_bad(int(chain[1]))
    assert m.live_ids(chain).tolist() == [-1, -1]


def test_vocabulary_scores_same_place_higher(image):
    voc = Vocabulary.load()
    assert voc.n_words == voc.k ** len(voc.levels) == 10000
    ex = OrbExtractor(1000, 1.2, 8, 20, 7)
    a, b = ex.extract(image[0]), ex.extract(image[1])
    other = ex.extract(cv2.imread(str(ROOT / "datasets/tum_fr3_cabinet_kf/rgb/0000_rgb_raw.jpg"), cv2.IMREAD_GRAYSCALE))
    wa = voc.words(a.desc)
    assert np.array_equal(wa, voc.words(a.desc)) and wa.max() < voc.n_words
    ba, bb, bo = voc.bow(wa), voc.bow(voc.words(b.desc)), voc.bow(voc.words(other.desc))
    assert bow_score(ba, ba) == pytest.approx(1.0)
    assert bow_score(ba, bb) > bow_score(ba, bo)


def test_config_rejects_unknown_and_missing_keys_naming_the_full_key():
    cam = SyntheticSequence(sensor="rgbd", n_frames=2, width=64, height=48).camera
    with pytest.raises(ConfigError):
        slam_frontend(cam, "rgbd", tracking={"no_such_key": 1})
    with pytest.raises(ConfigError):
        slam_frontend(cam, "fisheye")
    for key, value in (("ba_iterations", (0, 1)), ("ba_iterations", (4, -1)), ("ba_iterations_rgbd", (0, 0)),
                       ("ba_min_gain", 1.5), ("ba_window", 0),
                       ("triangulate_node_level", -1), ("triangulate_node_level", 9)):
        with pytest.raises(ConfigError, match=f"slam.local_mapping.{key}"):
            slam_frontend(cam, "rgbd", local_mapping={key: value})
    for key, value in (("fast_threshold", 0), ("floor_fast_threshold", 300), ("n_features", 0)):
        with pytest.raises(ConfigError, match=f"slam.features.{key}"):
            slam_frontend(cam, "rgbd", features={key: value})
    for key, value in (("rgbd_depth_noise", 0.0), ("rgbd_retry_depth_noise", -0.01), ("init_wait", -1),
                       ("min_init_points_late", 0)):
        with pytest.raises(ConfigError, match=f"slam.tracking.{key}"):
            slam_frontend(cam, "rgbd", tracking={key: value})
    conf = yaml.safe_load((ROOT / "conf/slam/orb.yaml").read_text())
    assert conf["_target_"] == "segs.slam.orb.OrbFrontend" and isinstance(C.slam_config(conf), C.OrbConfig)
    for group in C.GROUPS:  # every key of a group is in the YAML: the dataclasses have no defaults
        assert type(C.group_from_yaml(group)) is C.GROUPS[group]
    bad = {**conf, "tracking": {**conf["tracking"], "min_inlier": 30}}
    with pytest.raises(ConfigError, match=r"^slam\.tracking\.min_inlier: unknown key"):
        C.slam_config(bad)
    bad = {**conf, "tracking": {k: v for k, v in conf["tracking"].items() if k != "min_inliers"}}
    with pytest.raises(ConfigError, match=r"^slam\.tracking\.min_inliers: missing key$"):
        C.slam_config(bad)
    with pytest.raises(ConfigError, match=r"^slam\.mapping was renamed: use slam\.local_mapping$"):
        C.slam_config({**conf, "mapping": {"ba_window": 5}})
    known = yaml.safe_load((ROOT / "conf/slam/known_poses.yaml").read_text())
    assert isinstance(C.slam_config(known), C.KnownPosesConfig)
    with pytest.raises(ConfigError, match=r"^slam\.no_such_key: unknown key"):
        C.slam_config({**known, "no_such_key": 1})


@pytest.mark.parametrize("sensor", ["rgbd", "stereo"])
def test_local_ba_iterations_follow_the_sensor(sensor, monkeypatch):
    """RGB-D local BA runs mapping.ba_iterations_rgbd, the other sensors mapping.ba_iterations."""
    seq = SyntheticSequence(sensor=sensor, n_frames=10, width=320, height=240, trajectory="orbit", speed=0.3, seed=0)
    seen = []
    original = BundleAdjuster.run_two_pass

    def spy(self, poses, fixed, points, obs, iterations, min_gain=1e-5):
        seen.append(tuple(iterations))
        return original(self, poses, fixed, points, obs, iterations, min_gain)

    monkeypatch.setattr(BundleAdjuster, "run_two_pass", spy)
    fe = slam_frontend(seq.camera, sensor, local_mapping={"ba_iterations": (3, 2), "ba_iterations_rgbd": (2, 0)})
    run_sequence(fe, seq)
    assert len(seen) >= 2
    assert set(seen) == ({(2, 0)} if sensor == "rgbd" else {(3, 2)})


def test_triangulation_under_vocabulary_nodes_tracks_and_keeps_words():
    seq = SyntheticSequence(sensor="rgbd", n_frames=16, width=320, height=240, trajectory="orbit", speed=0.2, seed=0)
    fe = slam_frontend(seq.camera, "rgbd", local_mapping={"triangulate_node_level": 1})
    run = run_sequence(fe, seq)
    assert all(r.tracked for r in run.results) and len(fe.map.kfs) >= 2
    kf1, kf2 = (fe.map.kfs[k] for k in sorted(fe.map.kfs)[:2])
    assert len(kf1.words) == len(kf1.kp)
    n1, n2 = fe.local_mapping._nodes(kf1, kf2)
    assert np.array_equal(n1, kf1.words // 1000) and n2.max() < 10  # k = 10, depth 4: level-1 nodes
    assert fe.vocab.bow(kf1.words)[0].tolist() == fe.kfdb.bows[kf1.kf_id][0].tolist()


def test_threaded_mode_and_checkpoint_round_trip():
    seq = SyntheticSequence(sensor="rgbd", n_frames=24, width=320, height=240, trajectory="orbit", speed=0.3, seed=0)
    fe = slam_frontend(seq.camera, "rgbd", threaded=True)
    run_sequence(fe, seq, frames=range(12))
    state = fe.state_dict()  # stops the mapping thread
    single = slam_frontend(seq.camera, "rgbd")
    single.load_state_dict(state)
    run = run_sequence(single, seq, frames=range(12, 24))
    assert single.lost_frames() == [] and sorted(single.trajectory()) == list(range(24))
    assert all(r.tracked for r in run.results)


def _as_legacy_v1(state: dict) -> dict:
    """A state in the layout of "segs.orb.v1" checkpoints (before FramePoses and MapOutbox): the
    frontend's attributes, Tracker / LocalMapper / LoopCloser pickled whole with their config
    (written before TrackingState and the named thresholds: the state a plain string, config
    fields missing), frame poses as ("kf", id) / ("rel", id, rel) / ("abs", None, w2c) tuples."""
    import pickle

    from segs.slam.backend.local_mapping import LocalMapper
    from segs.slam.backend.loop_closing import LoopCloser
    from segs.slam.tracking.tracker import Tracker

    d = pickle.loads(state["blob"])
    d["tracker"] = dict(d["tracker"])
    poses = d["tracker"].pop("poses")
    traj = {i: ("abs", None, p.w2c) if p.kf_id is None else ("kf", p.kf_id) if p.rel is None else ("rel", p.kf_id, p.rel)
            for i, p in poses.poses.items()}  # fmt: skip
    tracking = C.group_from_yaml("tracking")
    for name in ("min_pose_inliers", "min_matches_ref", "local_map_ratio", "kf_min_tracked"):
        del tracking.__dict__[name]  # an old config: ignored (the loading frontend's own applies)
    objs = {}
    for name, cls, cfg in (("tracker", Tracker, tracking), ("mapper", LocalMapper, C.group_from_yaml("local_mapping")),
                           ("loop", LoopCloser, C.group_from_yaml("loop"))):
        obj = cls.__new__(cls)  # what unpickling an old component does
        obj.__dict__.update(d[name], cfg=cfg)
        objs[name] = obj
    objs["tracker"].state = "ok"
    outbox = d["outbox"].__getstate__()
    old = {"map": d["map"], "kfdb": d["kfdb"], **objs, "_traj": traj, "_lost": set(poses.lost),
           "_kf_frames": dict(poses.kf_frames), "_pending": outbox["pending"], "_pending_pids": outbox["chunks"]}
    return {"format": "segs.orb.v1", "blob": pickle.dumps(old)}


def test_tracking_state_enum_round_trips_checkpoint():
    """The tracker state is a TrackingState after a checkpoint round trip, and a checkpoint written
    before the Enum, FramePoses and MapOutbox ("segs.orb.v1") loads and tracks on exactly as the
    frontend that wrote it does."""
    from segs.slam.tracking.tracker import TrackingState

    seq = SyntheticSequence(sensor="rgbd", n_frames=12, width=320, height=240, trajectory="orbit", speed=0.3, seed=0)
    fe = slam_frontend(seq.camera, "rgbd")
    run_sequence(fe, seq, frames=range(6))
    assert fe.tracker.state is TrackingState.OK
    state = orb_v2_state(fe)
    new = slam_frontend(seq.camera, "rgbd")
    new.load_state_dict(fe.state_dict())
    assert new.tracker.state is TrackingState.OK
    old_fe = slam_frontend(seq.camera, "rgbd")
    old_fe.load_state_dict(_as_legacy_v1(state))
    assert old_fe.tracker.state is TrackingState.OK
    assert old_fe.tracker.cfg.min_pose_inliers == 10
    assert old_fe.trajectory().keys() == fe.trajectory().keys() and old_fe.keyframe_frames() == fe.keyframe_frames()
    run_sequence(fe, seq, frames=range(6, 12))
    run = run_sequence(old_fe, seq, frames=range(6, 12))
    assert old_fe.tracker.state is TrackingState.OK
    assert len(old_fe.lost_frames()) == 0, run
    want, got = fe.trajectory(), old_fe.trajectory()
    assert got.keys() == want.keys() and all(np.array_equal(got[i], want[i]) for i in want)


def test_frame_poses_follow_their_keyframe_and_read_the_legacy_tuples():
    from segs.slam.tracking.frame_poses import FramePoses

    kf_w2c = {0: np.eye(4), 1: np.eye(4)}
    kf_w2c[1][:3, 3] = [1.0, 0, 0]
    poses = FramePoses()
    w2c = np.eye(4)
    w2c[:3, 3] = [1.0, 2.0, 0]
    poses.record(5, kf_w2c[1].copy(), 1, None, kf_w2c.get)  # frame 5 is keyframe 1
    poses.record(6, w2c, None, 1, kf_w2c.get)  # relative to keyframe 1
    poses.record(7, w2c, None, None, kf_w2c.get)  # no reference keyframe: absolute
    poses.record(8, None, None, 1, kf_w2c.get)  # lost
    assert poses.lost_frames() == [8] and poses.keyframe_frames([0, 1]) == {1: 5} and len(poses) == 3
    moved = np.eye(4)
    moved[:3, 3] = [3.0, 0, 0]
    kf_w2c[1] = moved  # BA moved keyframe 1: its frames follow, the absolute one stays
    traj = poses.trajectory(kf_w2c.get)
    assert np.allclose(traj[5], moved) and np.allclose(traj[6][:3, 3], [3.0, 2.0, 0]) and np.allclose(traj[7], w2c)
    assert poses.w2c(7, kf_w2c.get) is None  # no keyframe to recompose from
    legacy = FramePoses.from_legacy({5: ("kf", 1), 6: ("rel", 1, poses.poses[6].rel), 7: ("abs", None, w2c)}, {8}, {1: 5})
    assert legacy.lost == poses.lost and legacy.kf_frames == poses.kf_frames
    assert all(np.array_equal(legacy.trajectory(kf_w2c.get)[i], traj[i]) for i in traj)
    del kf_w2c[1]
    assert sorted(poses.trajectory(kf_w2c.get)) == [7]  # a keyframe unknown to the map: its frames left out


def test_keypoint_depth_lookup_is_the_3x3_dilation_and_erosion_test():
    """FrameBuilder._lookup_depth (3x3 neighbourhoods gathered at the keypoints) against the
    whole-image dilation / erosion it replaces, with holes, depth edges and image borders."""
    import cv2

    from segs.slam.features.frame import FrameBuilder

    rng = np.random.default_rng(5)
    depth = (2.0 + 0.002 * np.arange(64) + rng.uniform(0, 0.01, (48, 64))).astype(np.float32)  # a slanted wall
    depth[rng.random(depth.shape) < 0.02] = 0.0  # holes
    depth[:, 30:] += 0.5  # an occluding edge
    uv = np.r_[rng.uniform(-2, 66, (400, 2)) * [1, 0.75], [[0, 0], [63, 47], [63.4, 0.2], [-0.6, 47.6]]]
    k = np.ones((3, 3), np.uint8)
    x = np.clip(np.rint(uv[:, 0]).astype(np.int64), 0, 63)
    y = np.clip(np.rint(uv[:, 1]).astype(np.int64), 0, 47)
    want = depth[y, x].astype(np.float64)
    hi, lo = cv2.dilate(depth, k)[y, x], cv2.erode(depth, k)[y, x]
    want[(lo <= 0) | (hi - lo > 0.05 * want)] = 0.0
    got = FrameBuilder._lookup_depth(depth, uv, 0.05)
    assert np.array_equal(got, want) and 0 < (got > 0).sum() < len(uv)


def test_triangulation_parallax_per_sensor():
    """Monocular triangulation takes mapping.min_parallax_deg_mono, stereo / RGB-D
    mapping.min_parallax_deg (rays without depth)."""
    seq = SyntheticSequence(sensor="rgbd", n_frames=2, width=160, height=120, seed=0)
    mapping = {"min_parallax_deg": 1.0, "min_parallax_deg_mono": 3.0}
    for sensor, deg in (("mono", 3.0), ("rgbd", 1.0)):
        fe = slam_frontend(seq.camera, sensor, local_mapping=mapping)
        assert fe.local_mapping.cos_parallax == pytest.approx(np.cos(np.radians(deg)))
