"""Held-out test frames never feed the map: not as training views, not as structure."""
from __future__ import annotations

from segs.train import build, step_batches


def test_points_created_by_held_out_keyframes_never_reach_the_mapper(tiny_cfg):
    # known poses: every 3rd frame is a keyframe and every 3rd frame is held out, so the
    # held-out frames are keyframes of the frontend whose keypoints it lifts with their depth
    cfg = tiny_cfg("trainer.max_steps=20", "callbacks.periodic_checkpoint.every_n_steps=0", "eval.enabled=false")
    t = build(cfg)
    run, module, bridge, trainer = t.state, t.module, t.bridge, t.trainer
    given = []
    add_points = module.add_points
    module.add_points = lambda xyz, rgb, kf_ids: given.extend(kf_ids.tolist()) or add_points(xyz, rgb, kf_ids)
    trainer.fit(module, step_batches(20))
    bridge.complete_sequence()
    held = {k for k, i in run.keyframe_frames().items() if i % 3 == 0}
    assert held and set(run.held_out_keyframes()) == held
    assert given and not held & set(given)
    assert run.held_out_points > 0  # the frontend did make them: the run kept them out
    assert set(run.test_frames()) >= {i for i in run.trajectory() if i % 3 == 0}

