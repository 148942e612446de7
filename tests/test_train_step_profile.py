"""bench/train_step.py --profile: wall time per step against the device kernels' time (logic only:
no timing is asserted). The CUDA case runs where a device and gsplat are present."""
from __future__ import annotations

import pytest

from conftest import load_bench
from segs.raster import available_backends


@pytest.fixture(scope="module")
def train_step():
    return load_bench("train_step")


def test_profile_on_cpu_times_the_steps_and_names_the_host_ops(train_step):
    row = train_step.profiled(schedule=60, warmup=5, iters=6, backend="cpu", device="cpu", experiment="sample")
    assert row["wall"] > 0 and row["anchors"] > 0
    assert row["device"] is None and row["device_share"] is None and row["kernels_per_step"] is None
    assert row["top_host_ops_ms"] and all(v >= 0 for v in row["top_host_ops_ms"].values())
    assert any("Rasterize" in k for k in row["top_host_ops_ms"])


def test_profile_stops_with_a_message_when_the_schedule_is_too_short(train_step):
    with pytest.raises(SystemExit, match="raise --schedule"):
        train_step.profiled(schedule=8, warmup=5, iters=6, backend="cpu", device="cpu", experiment="sample")


@pytest.mark.cuda
@pytest.mark.skipif("cuda" not in available_backends(), reason="needs CUDA and gsplat (pip install 'segs[gpu]')")
def test_profile_on_cuda_counts_kernel_time_within_the_wall_time(train_step):
    row = train_step.profiled(schedule=60, warmup=5, iters=6, backend="cuda", device="cuda", experiment="sample")
    assert 0 < row["device"] and row["kernels_per_step"] > 0
    assert row["device_share"] <= 1.05  # kernels on one stream cannot outlast the steps (profiler rounding)
