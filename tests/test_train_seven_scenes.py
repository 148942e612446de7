"""segs.train end to end with the ORB frontend in the loop on real 30 Hz frames (a short slice of
the shared 7-Scenes sequence; skipped where the data is absent)."""
from __future__ import annotations

import json

import numpy as np
import torch

from segs.config import compose
from segs.data.poses import poses_from_tq
from segs.train import run


def test_train_with_orb_frontend_on_real_frames(seven_scenes_root, tmp_path):
    out = tmp_path / "run"
    cfg = compose([
        "+experiment=seven_scenes_rgbd", f"data.root={seven_scenes_root}", "data.frames=[150,210]", "data.downscale=2",
        "trainer.max_steps=60", "logger=none", "callbacks.slam_bridge.progress=false",
        "~callbacks.progress_bar", "trainer.enable_progress_bar=false", "callbacks.image_logger.every_n_steps=0",
        "eval.save_renders=1", "eval.progress=false",
    ], output_dir=str(out))
    run(cfg)
    m = json.loads((out / "metrics.json").read_text())
    assert m["status"] == "finished" and m["frames"] == 60
    assert m["frames_tracked"] == 60 and m["lost_frames"] == 0
    assert m["keyframes"] >= 4 and m["test_views"] == 60 - m["training_views"] > 0
    assert np.isfinite(m["psnr"]) and m["psnr"] > 12 and 0 < m["ssim"] <= 1
    assert m["ate_rmse_m"] < 0.05 and m["anchors"] > 0
    # frames 150-199 also exist as lossless PNGs: the test views among them are scored against both
    assert 0 < m["lossless_views"] <= 50 and np.isfinite(m["psnr_lossless"])
    assert m["psnr_jpeg_vs_lossless"] > 33  # the JPEG's own error (36 dB at full size), the PSNR ceiling

    # the module trained on the frontend's final keyframe poses (refreshed by local BA and finish)
    est = np.loadtxt(out / "trajectory.txt")
    c2w = dict(zip(np.rint(est[:, 0] * 30).astype(int).tolist(), poses_from_tq(est[:, 1:4], est[:, 4:8])))
    ckpt = torch.load(out / "checkpoints" / "final.ckpt", map_location="cpu", weights_only=False)
    store = ckpt["segs"]["store"]["frames"]
    assert len(store) == m["training_views"]
    for kf in store:
        w2c = kf["w2c"].double().numpy()
        frame_number = 150 + kf["frame_index"]
        np.testing.assert_allclose(np.linalg.inv(w2c), c2w[frame_number], atol=2e-4)
