"""Importing segs changes nothing process-wide; its programs apply the process settings
(OMP_WAIT_POLICY=PASSIVE, glibc's freed memory kept) themselves, before torch loads."""
from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import TINY

ROOT = Path(__file__).resolve().parents[1]
# 48 MB: above glibc's largest dynamic mmap threshold (32 MB), below the kept-memory setting (64 MB)
PROBE = """
import ctypes, json, os, sys, warnings

class MallInfo2(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks",
                                                "uordblks", "fordblks", "keepcost")]

libc = ctypes.CDLL("libc.so.6")
libc.mallinfo2.restype, libc.malloc.restype, libc.free.argtypes = MallInfo2, ctypes.c_void_p, [ctypes.c_void_p]

def mapped(size=48 << 20):
    before = libc.mallinfo2().hblks
    p = libc.malloc(size)
    after = libc.mallinfo2().hblks
    libc.free(p)
    return after > before

import segs, segs.config, segs.track, segs.train  # segs.train loads torch
out = {"imported": [os.environ.get("OMP_WAIT_POLICY"), mapped(), "torch" in sys.modules]}
from segs import process_settings
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    process_settings.apply()
out["applied"] = [os.environ.get("OMP_WAIT_POLICY"), mapped(), process_settings.malloc_setting()]
out["warnings"] = [str(w.message) for w in caught]
print(json.dumps(out))
"""


def _env(**extra: str) -> dict:
    """This environment without the settings (conftest applied them to this process)."""
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT", "SEGS_MALLOC")}
    return {**env, "PYTHONPATH": str(ROOT / "src"), **extra}


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallinfo2 / mallopt")
def test_importing_segs_changes_nothing_and_apply_sets_both_settings():
    res = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, env=_env(), timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    out = json.loads(res.stdout.splitlines()[-1])
    # import: no policy, a 48 MB block is a fresh mapping (glibc's default), torch loaded
    assert out["imported"] == [None, True, True]
    assert out["applied"] == ["PASSIVE", False, "kept"]
    # torch was loaded first: its OpenMP threads never see the policy, and apply() says so
    assert len(out["warnings"]) == 1 and "after torch was imported" in out["warnings"][0]


def test_segs_malloc_default_opts_out_of_the_allocator_setting():
    code = "from segs import process_settings as p; p.apply(); print(p.malloc_setting())"
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=_env(SEGS_MALLOC="default"), timeout=120)
    assert res.returncode == 0 and res.stdout.split() == ["default"], res.stderr[-2000:]


SPIN_PROBE = """
import os
from segs import process_settings as p
p.idle_share = lambda seconds=0.1: {idle}
p.apply()
print(os.environ.get("OMP_WAIT_POLICY"), os.environ.get("GOMP_SPINCOUNT"))
"""


@pytest.mark.parametrize("idle, preset, expected", [
    (0.9, {}, "PASSIVE 1000"),  # idle CPUs: a short spin before sleeping
    (0.5, {}, "PASSIVE None"),  # busy: threads sleep at once
    (None, {}, "PASSIVE None"),  # /proc/stat unreadable
    (0.9, {"GOMP_SPINCOUNT": "7"}, "PASSIVE 7"),  # the user's spin count is kept
    (0.9, {"OMP_WAIT_POLICY": "ACTIVE"}, "ACTIVE None"),  # the user's policy: nothing added
])  # fmt: skip
def test_a_short_spin_only_when_the_cpus_are_idle_and_nothing_is_set(idle, preset, expected):
    code = SPIN_PROBE.format(idle=idle)
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=_env(**preset), timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    assert res.stdout.strip() == expected


@pytest.mark.skipif(not Path("/proc/stat").is_file(), reason="/proc/stat")
def test_idle_share_is_a_share_of_the_cpus_time():
    from segs.process_settings import idle_share

    share = idle_share(0.05)
    assert share is not None and 0.0 <= share <= 1.0


def _provenance(result: Path) -> dict:
    return json.loads(result.read_text())["provenance"]


def test_segs_track_applies_the_settings(tmp_path):
    args = ["+experiment=synthetic", "slam=known_poses", "data.n_frames=6", "data.width=96", "data.height=72",
            f"hydra.run.dir={tmp_path}"]
    res = subprocess.run([sys.executable, "-m", "segs.track", *args], capture_output=True, text=True, env=_env(), cwd=ROOT,
                         timeout=300)  # fmt: skip
    assert res.returncode == 0, res.stderr[-2000:]
    p = _provenance(tmp_path / "tracking.json")
    assert p["threads"]["OMP_WAIT_POLICY"] == "PASSIVE" and p["malloc"] == "kept"


@pytest.mark.slow
def test_segs_train_applies_the_settings_before_torch_loads(tmp_path):
    args = [*TINY, "trainer.max_steps=3", "eval.write_ply=false", "callbacks.periodic_checkpoint.every_n_steps=0",
            f"hydra.run.dir={tmp_path}"]
    res = subprocess.run([sys.executable, "-m", "segs.train", *args], capture_output=True, text=True, env=_env(), cwd=ROOT,
                         timeout=300)  # fmt: skip
    assert res.returncode == 0, res.stderr[-2000:]
    assert "after torch was imported" not in res.stderr
    p = _provenance(tmp_path / "metrics.json")
    assert p["threads"]["OMP_WAIT_POLICY"] == "PASSIVE" and p["malloc"] == "kept"


SRC = ROOT / "src" / "segs"
# programs whose imports load torch: the guarded call is their first statement
TORCH_PROGRAMS = ("train.py", "view.py")
# programs whose imports do not: the call opens their __main__ block
PROGRAMS = ("track.py", "pipeline/process.py", "slam/backend/ba_process.py", "slam/map/vocabulary.py")


def _main_blocks(path: Path) -> list[tuple[int, ast.If]]:
    """(position among the module's statements, block) of each `if __name__ == "__main__":`."""
    body = ast.parse(path.read_text()).body
    return [(i, node) for i, node in enumerate(body) if isinstance(node, ast.If) and ast.unparse(node.test) == "__name__ == '__main__'"]


def _applies_first(block: ast.If) -> bool:
    calls = [ast.unparse(s) for s in block.body if isinstance(s, ast.Expr)]
    return bool(calls) and calls[0] == "process_settings.apply()"


@pytest.mark.parametrize("program", TORCH_PROGRAMS)
def test_programs_that_load_torch_apply_the_settings_before_their_imports(program):
    body = ast.parse((SRC / program).read_text()).body
    first = next(i for i, node in enumerate(body)
                 if not (isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant))  # the docstring
                 and not (isinstance(node, ast.ImportFrom) and node.module == "__future__"))  # fmt: skip
    blocks = _main_blocks(SRC / program)
    assert blocks and blocks[0][0] == first, f"{program}: the guarded apply() is not the first statement"
    assert any(ast.unparse(s) == "process_settings.apply()" for s in blocks[0][1].body)


@pytest.mark.parametrize("program", PROGRAMS)
def test_other_programs_apply_the_settings_first_in_their_main_block(program):
    blocks = _main_blocks(SRC / program)
    assert blocks and _applies_first(blocks[-1][1]), f"{program}: __main__ does not start with process_settings.apply()"


# 400 blocks of 256 kB (glibc heap memory under apply()'s thresholds, written: resident), a small
# block allocated after them (pins the heap's top), the 400 freed: kept by the heap until released
RELEASE_PROBE = """
import json
from segs import process_settings
process_settings.apply()

def rss_mb():
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS")) / 1024

blocks = [bytearray(256 << 10) for _ in range(400)]
pin = bytearray(1 << 10)
del blocks
kept = rss_mb()
released = process_settings.release_free_memory()
print(json.dumps({"released": released, "kept_mb": kept, "after_mb": rss_mb()}))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc_trim")
def test_release_free_memory_gives_the_kept_heap_back():
    res = subprocess.run([sys.executable, "-c", RELEASE_PROBE], capture_output=True, text=True, env=_env(), timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    out = json.loads(res.stdout.splitlines()[-1])
    assert out["released"] is True
    assert out["kept_mb"] - out["after_mb"] > 80, out  # of the 100 MB freed
