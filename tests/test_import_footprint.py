"""What the default run does not load: libraries whose import costs resident memory and that a
CPU training run never calls (issue 40, docs/decisions/029-peak-memory.md). Checked in a fresh
interpreter: this test process imports them itself."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# imports segs.train, then computes the CPU float32 photometric loss (the fused SSIM kernel) and
# its gradient, as a training step does; prints which of kornia (its blur runs off the CPU only)
# and evo's file module with rosbags (trajectory files are read and written after training) are loaded
PROBE = """
import json, sys
from segs import process_settings
process_settings.apply()
import torch
import segs.train
from segs.modules import losses
from segs.raster import fused_ssim_available
g = torch.Generator().manual_seed(0)
gt = torch.rand(24, 32, 3, generator=g)
render = gt.add(0.1 * torch.randn(24, 32, 3, generator=g)).clamp(0, 1).requires_grad_()
fused = fused_ssim_available(render.permute(2, 0, 1), 11)
losses.photometric(render, gt, 0.2)["photometric"].backward()
print(json.dumps({"fused": fused, "loaded": sorted(m for m in ("kornia", "evo.tools.file_interface", "rosbags") if m in sys.modules)}))
"""


def test_segs_train_and_its_cpu_loss_import_neither_kornia_nor_evos_file_module():
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src") + os.pathsep + os.environ.get("PYTHONPATH", "")}
    res = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, env=env, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    out = json.loads(res.stdout.strip().splitlines()[-1])
    if not out["fused"]:
        pytest.skip("the C++ kernels cannot be built here: the loss takes kornia's blur")
    assert out["loaded"] == [], f"loaded by `import segs.train` and the CPU loss: {out['loaded']}"
