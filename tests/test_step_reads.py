"""The training step reads back from the device only what Scaffold-GS's decoding needs (on a GPU
each read waits for the device): the frustum and the opacity culls, and on one step in LOSS_READ
(none of those counted here) the rasterizer's check of the values. Counted on the CPU, where the
same calls are made."""
from __future__ import annotations

import collections
import traceback

from torch.overrides import TorchFunctionMode

READS = {"item", "tolist", "__bool__", "__float__", "__int__", "__index__", "nonzero", "numpy", "cpu"}


class Reads(TorchFunctionMode):
    """Counts the tensor reads made from segs's own code (not inside a rasterizer backend)."""

    def __init__(self):
        super().__init__()
        self.sites: collections.Counter = collections.Counter()

    def __torch_function__(self, func, types, args=(), kwargs=None):
        name = getattr(func, "__name__", "")
        if name in READS:
            frames = [f for f in traceback.extract_stack()[:-1] if "/segs/" in f.filename]
            if frames and "_backend" not in frames[-1].filename:
                f = frames[-1]
                self.sites[(f.filename.rsplit("/segs/", 1)[1], name)] += 1
        return func(*args, **(kwargs or {}))


def test_a_training_step_reads_only_the_culls(tiny_cfg):
    from segs.train import build, step_batches

    cfg = tiny_cfg("trainer.max_steps=60", "trainer.log_every_n_steps=1000", "callbacks.periodic_checkpoint.every_n_steps=0",
                   "eval.enabled=false")  # fmt: skip
    t = build(cfg)
    module, steps = t.module, []
    training_step = module.training_step

    def counted(batch, batch_idx):
        with Reads() as reads:
            out = training_step(batch, batch_idx)
        steps.append(reads.sites)
        return out

    module.training_step = counted
    t.trainer.fit(module, step_batches(60))
    # after the frames are fed (the first 20 %) and each view was drawn once (its pose vector is
    # made once per pose), on the steps without densification
    plain = [s for step, s in enumerate(steps) if step >= 40 and step % module.model._interval()]
    assert len(plain) >= 15
    expected = {("modules/anchors.py", "nonzero"): 2}
    assert all(dict(s) == expected for s in plain), [dict(s) for s in plain if dict(s) != expected][:2]
    assert len(module.loss_history) == 60  # the losses, read in one batch
