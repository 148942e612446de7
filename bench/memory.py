"""Where a training run's resident memory goes: RSS at each stage of `python -m segs.train`.

    python bench/memory.py [OVERRIDE ...]          # the default run (the bundled sample)
    python bench/memory.py +experiment=seven_scenes_rgbd data.frames=[100,250] slam=known_poses

Runs segs.train.run in this process with the overrides (the defaults' loggers, bars and
callbacks included) and records at every stage: the resident set (VmRSS) split into anonymous
memory and mapped files (libraries), the C heap (glibc mallinfo2: bytes in use and bytes free
but kept), and the highest RSS since the previous stage (a sampler thread, every 20 ms). Stages:
`import torch`, `import segs.train`, the run built (sequence, frontend, module, trainer), the
initial keyframes fed, steps 1 / 100 / 500 / 1,000 / 1,500 / the last, the final checkpoint, the
heap's free pages released (segs.process_settings.release_free_memory) and the evaluation. The
peak is the kernel's (ru_maxrss). MB = 10^6 bytes. Writes outputs/bench/memory.json (the stages,
the peak, the machine and commit record).
"""
from __future__ import annotations

import ctypes
import resource
import sys
import threading
import time

import _harness

_harness.apply_process_settings()  # before torch loads (the first stage measures its import)

MB = 1e6
STEPS = (1, 100, 500, 1000, 1500)


class _MallInfo2(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in "arena ordblks smblks hblks hblkhd usmblks fsmblks uordblks fordblks keepcost".split()]


def _status() -> dict[str, float]:
    """VmRSS, RssAnon, RssFile of this process in MB."""
    out = {}
    with open("/proc/self/status") as f:
        for line in f:
            key, value = line.split(":", 1)
            if key in ("VmRSS", "RssAnon", "RssFile"):
                out[key] = int(value.split()[0]) * 1024 / MB
    return out


class Stages:
    """Stage marks with the RSS, heap and highest RSS since the previous mark."""

    def __init__(self):
        try:
            self._libc = ctypes.CDLL("libc.so.6")
            self._libc.mallinfo2.restype = _MallInfo2
        except (OSError, AttributeError):  # not glibc: no heap figures
            self._libc = None
        self.rows: list[dict] = []
        self._high = 0.0
        self._t0 = time.perf_counter()
        threading.Thread(target=self._sample, daemon=True).start()

    def _sample(self) -> None:
        while True:
            self._high = max(self._high, _status()["VmRSS"])
            time.sleep(0.02)

    def mark(self, stage: str) -> None:
        s = _status()
        heap = self._libc.mallinfo2() if self._libc else None
        self.rows.append({"stage": stage, "seconds": time.perf_counter() - self._t0, "rss": s["VmRSS"], "anon": s["RssAnon"],
                          "files": s["RssFile"], "heap_used": heap.uordblks / MB if heap else None,
                          "heap_free": heap.fordblks / MB if heap else None, "high_since_last": max(self._high, s["VmRSS"])})  # fmt: skip
        self._high = 0.0

    def table(self) -> str:
        f = lambda v: "-" if v is None else f"{v:.0f}"  # noqa: E731
        lines = ["| stage | s | RSS MB | anonymous | files | C heap in use / free | highest since the previous stage |",
                 "|---|---|---|---|---|---|---|"]  # fmt: skip
        for r in self.rows:
            lines.append(f"| {r['stage']} | {r['seconds']:.1f} | {r['rss']:.0f} | {r['anon']:.0f} | {r['files']:.0f} | "
                         f"{f(r['heap_used'])} / {f(r['heap_free'])} | {r['high_since_last']:.0f} |")  # fmt: skip
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / MB
        return "\n".join(lines + ["", f"peak RSS (ru_maxrss): {peak:.0f} MB"])


def main(overrides: list[str]) -> None:
    stages = Stages()
    import torch  # noqa: F401

    stages.mark("import torch")
    import lightning as L

    import segs.evaluation
    import segs.train as train
    from segs import process_settings
    from segs.config import compose

    stages.mark("import segs.train")
    cfg = compose(overrides, output_dir=f"outputs/bench/memory_{time.strftime('%Y%m%d_%H%M%S')}")
    build, save_final, render = train.build, train.save_final, segs.evaluation.render_test_views
    release = process_settings.release_free_memory

    class Marks(L.Callback):
        def on_train_start(self, trainer, module):
            stages.mark("initial keyframes fed")

        def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx):
            step = trainer.global_step
            if step in STEPS or step == trainer.max_steps:
                stages.mark(f"step {step:,} ({module.counts().anchors:,} anchors)")

    def built(*args, **kwargs):
        out = build(*args, **kwargs)
        stages.mark("run built (sequence, frontend, module, trainer)")
        out.trainer.callbacks.append(Marks())
        return out

    def saved(*args, **kwargs):
        out = save_final(*args, **kwargs)
        stages.mark("final checkpoint written")
        return out

    def released():
        out = release()
        stages.mark("heap's free pages released")
        return out

    def rendered(*args, **kwargs):
        out = render(*args, **kwargs)
        stages.mark("test views rendered and scored")
        return out

    train.build, train.save_final, segs.evaluation.render_test_views = built, saved, rendered
    process_settings.release_free_memory = released
    metrics = train.run(cfg)
    stages.mark("evaluation written")
    print(f"\npython bench/memory.py {' '.join(overrides)}: PSNR {metrics['psnr']:.2f} dB, {metrics['anchors']:,} anchors\n")
    print(stages.table())
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / MB
    out = _harness.write_json(_harness.OUTPUTS / "memory.json", {**_harness.record(), "overrides": overrides, "stages": stages.rows,
                                                                 "peak_rss_mb": peak, "psnr": metrics["psnr"]})  # fmt: skip
    print(f"wrote {out}")


if __name__ == "__main__":
    main(sys.argv[1:])
