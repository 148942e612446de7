"""Place recognition with the shipped vocabulary on real 7-Scenes frames, which it was not trained
on: database retrieval (the protocol of bench/place_recognition.py) and relocalization."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from conftest import load_bench
from segs.config import slam_frontend
from segs.data.frame import Frame
from segs.slam.geometry import inv_se3
from segs.slam.map.vocabulary import Vocabulary

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def bench():
    return load_bench("place_recognition", "place_recognition")


@pytest.fixture(scope="module")
def seq(bench, seven_scenes_root):
    return bench.open_7scenes(seven_scenes_root)


def test_retrieval_finds_covisible_frames_of_the_revisit(bench, seq):
    # every third frame as a query (the documented figures use every frame)
    p = bench.protocol(seq, query_step=3)
    assert len(p["queries"]) >= 80
    r = bench.recall(Vocabulary.load(), p)
    # measured: recall@1 0.77, recall@5 0.93 on 96 queries, a random pick 0.22
    assert r["chance@1"] < 0.3
    assert r["recall@1"] >= 0.65 and r["recall@5"] >= 0.85


def _blank(seq, index: int) -> Frame:
    """A grey frame without depth at `index` (tracking is lost on it)."""
    f = seq[index]
    return Frame(index, f.timestamp, np.full_like(f.rgb, 0.5), f.camera, depth=np.zeros_like(f.depth))


def test_relocalization_after_a_jump_to_the_revisit(seq):
    """Map frames 250-289 (RGB-D), lose tracking, then show frames of the revisit 3-9 s later:
    each is relocalized through the database (not the recent keyframe: lost > 30 frames ago)."""
    fe = slam_frontend(seq.camera, "rgbd")
    for i in range(250, 290):
        fe.process(seq[i])
    assert fe.lost_frames() == []
    prev = 289
    for q in (480, 520, 560):
        assert not fe.process(_blank(seq, prev + 1)).tracked
        assert q - (prev + 1) > fe.cfg.tracking.recent_lost
        assert fe.process(seq[q]).tracked, f"frame {q} not relocalized"
        assert fe.tracker.last_reloc_frame == q
        # pose against the map's first frame, vs ground truth (the camera moved 0.27-0.54 m
        # from the last mapped frame: a restart at the last pose would be far off)
        est = fe.trajectory()[250] @ inv_se3(fe.trajectory()[q])
        gt = inv_se3(seq.gt_poses[250]) @ seq.gt_poses[q]
        err = inv_se3(est) @ gt
        angle = np.degrees(np.arccos(np.clip((np.trace(err[:3, :3]) - 1) / 2, -1, 1)))
        assert np.linalg.norm(est[:3, 3] - gt[:3, 3]) < 0.10 and angle < 4.0, (q, est, gt)
        assert np.linalg.norm(seq.gt_poses[q][:3, 3] - seq.gt_poses[289][:3, 3]) > 0.2
        prev = q
