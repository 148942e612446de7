"""Checkpoint states of the bridge written before segs.state.v3, in the current layout.

Before v3 the bridge saved its own fields (cursor, credit, trained_frames, held_out_keyframes,
processed, ..., the frontend's state) instead of a RunState; the frontend's own old formats are
converted by the frontends (segs.slam.legacy, segs.pipeline.process).
"""
from __future__ import annotations

import numpy as np

from segs.errors import ConfigError
from segs.slam.base import STATE_FORMAT


def bridge_state(state: dict) -> dict:
    """A SlamBridge state of any version -> the v3 layout ({"format", "run", "credit",
    "frames_per_step"}); ConfigError naming the format for one this version cannot read."""
    fmt = state.get("format")
    if fmt == STATE_FORMAT:
        return state
    if fmt is not None or "cursor" not in state:
        raise ConfigError(f"ckpt_path: the run state has format {fmt!r}; this version reads {STATE_FORMAT} and the "
                          "bridge states before it")  # fmt: skip
    frontend = state["frontend"]
    if frontend.get("format") == "segs.process.v1":  # slam_mode=process | live: the source's own state
        source = frontend
    else:
        source = {"mode": "interleaved", "cursor": int(state["cursor"]), "frames_done": int(state.get("processed", 0)),
                  "process_seconds": float(state.get("process_seconds", 0.0)), "frontend": frontend}  # fmt: skip
    trained = {int(k): int(v) for k, v in state["trained_frames"].items()}
    held = [int(k) for k in state["held_out_keyframes"]]
    ids = sorted(set(trained) | set(held))
    # before v3 neither the poses nor the held-out keyframes' frames were kept: NaN poses, frame -1
    registry = {"kf_id": np.array(ids, np.int64), "frame_index": np.array([trained.get(k, -1) for k in ids], np.int64),
                "w2c": np.full((len(ids), 4, 4), np.nan), "trained": np.array([k in trained for k in ids], bool)}  # fmt: skip
    points = state.get("map_points") or {"points": np.zeros((0, 3)), "colors": np.zeros((0, 3), np.float32),
                                         "kf_ids": np.zeros(0, np.int64)}  # fmt: skip
    run = {"source": source, "keyframes": registry, "held_out_points": int(state.get("held_out_points", 0)),
           "finished": bool(state["finished"]), "map_points": points}  # fmt: skip
    return {"format": STATE_FORMAT, "run": run, "credit": float(state["credit"]), "frames_per_step": state["frames_per_step"]}
