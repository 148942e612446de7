"""What the 7-Scenes frames offer AfME and FPR: exposure changes and JPEG noise in FPR's band.

1. Exposure: the intensity ratio of the same surface points seen in frames i and i+gap (frame
   i's registered depth and the ground-truth poses map its pixels into frame i+gap; median ratio
   over the pixels of a pair), for gaps of 5 to 120 frames. AfME can only help where this moves.
2. JPEG: for the frames that also exist losslessly (150-199 of the shared slice), the energy of
   the JPEG error (JPEG - lossless) inside FPR's high-pass band, relative to the lossless image's
   energy in the same band, at FPR's three pyramid scales; at 640x480 and 320x240. FPR pulls the
   render's high-frequency amplitudes toward the JPEG's, artefacts included.

    python bench/seven_scenes_signal.py [--root ../shared/data/7scenes_redkitchen_0000_0599]

JSON: outputs/bench/seven_scenes_signal.json.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import _harness

_harness.apply_process_settings()  # before torch loads

import numpy as np
import torch
import torch.nn.functional as F

from segs.data.seven_scenes import SevenScenesSequence
from segs.modules.fpr import highpass_mask, spectrum

ROOT = _harness.ROOT


def same_point_ratio(a, b) -> float | None:
    """Median grey-level ratio b / a over frame a's pixels with depth that land inside frame b."""
    c = a.camera
    v, u = np.nonzero(a.depth > 0)
    z = a.depth[v, u]
    X = np.stack([(u - c.cx) / c.fx * z, (v - c.cy) / c.fy * z, z, np.ones_like(z)], 1)
    Y = X @ (np.linalg.inv(b.pose_c2w) @ a.pose_c2w).T
    ub, vb = c.fx * Y[:, 0] / Y[:, 2] + c.cx, c.fy * Y[:, 1] / Y[:, 2] + c.cy
    ok = (ub > 1) & (ub < c.width - 2) & (vb > 1) & (vb < c.height - 2) & (Y[:, 2] > 0.1)
    if ok.sum() < 5000:  # too little overlap
        return None
    ga = a.rgb.mean(2)[v[ok], u[ok]]
    gb = b.rgb.mean(2)[vb[ok].round().astype(int), ub[ok].round().astype(int)]
    keep = (ga > 0.05) & (gb > 0.05) & (ga < 0.95)  # not black, not saturated
    return float(np.median(gb[keep] / ga[keep]))


def exposure(seq, gaps=(5, 30, 60, 120), every: int = 15) -> dict:
    """gap -> percentiles (5, 50, 95) of the same-point intensity ratio over frame pairs."""
    out = {}
    for gap in gaps:
        r = [x for x in (same_point_ratio(seq[i], seq[i + gap]) for i in range(0, len(seq) - gap, every)) if x is not None]
        out[gap] = {"pairs": len(r), "p5": float(np.percentile(r, 5)), "median": float(np.median(r)), "p95": float(np.percentile(r, 95))}
    return out


def jpeg_in_fpr_band(seq, scales: int = 3, hp_ratio: float = 0.4) -> list[float]:
    """Per FPR scale: mean over lossless frames of |FFT(JPEG - lossless)|^2 / |FFT(lossless)|^2 in the high-pass band."""
    rows = []
    for i in range(len(seq)):
        clean = seq.lossless_rgb(i)
        if clean is None:
            continue
        jpg = torch.from_numpy(seq[i].rgb).permute(2, 0, 1)[None].float()
        ref = torch.from_numpy(np.ascontiguousarray(clean)).permute(2, 0, 1)[None].float()
        row = []
        for s in range(scales):
            size = (jpg.shape[-2] // 2**s, jpg.shape[-1] // 2**s)
            a, b = (F.interpolate(x, size=size, mode="bilinear", align_corners=False) if s else x for x in (jpg, ref))
            m = highpass_mask(*size, hp_ratio)
            row.append(float((m * spectrum(a - b)).abs().pow(2).sum() / (m * spectrum(b)).abs().pow(2).sum()))
        rows.append(row)
    return np.mean(rows, 0).tolist()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--root", type=Path, default=_harness.SEVEN_SCENES)
    p.add_argument("--out", type=Path, default=_harness.OUTPUTS / "seven_scenes_signal.json")
    args = p.parse_args()
    result = {"exposure": exposure(SevenScenesSequence(args.root, sensor="rgbd")), "jpeg_in_fpr_band": {}}
    for gap, r in result["exposure"].items():
        print(f"frames {gap:3d} apart: same-point intensity ratio p5 {r['p5']:.3f}, median {r['median']:.3f}, p95 {r['p95']:.3f} ({r['pairs']} pairs)")
    for ds in (1, 2):
        seq = SevenScenesSequence(args.root, sensor="rgbd", downscale=ds)
        band = jpeg_in_fpr_band(seq)
        result["jpeg_in_fpr_band"][f"{seq.camera.width}x{seq.camera.height}"] = band
        print(f"{seq.camera.width}x{seq.camera.height}: JPEG error energy in FPR's high-pass band, per scale: "
              + ", ".join(f"{100 * x:.1f} %" for x in band) + " of the lossless image's")  # fmt: skip
    _harness.write_json(args.out, result)


if __name__ == "__main__":
    main()
