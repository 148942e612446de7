"""The decoder average (segs.modules.decoder_average): renders outside training decode with an
exponential moving average of the decoders' and AfME's weights; training with the live ones."""
import pytest
import torch
from torch import nn

from segs.config import model_node
from segs.data.frame import Camera
from segs.modules.config import build_model
from segs.modules.decoder_average import DecoderAverage
from segs.modules.scene_model import View


def test_the_average_starts_as_the_given_weights_and_follows_the_live_ones_by_the_decay():
    live = nn.Linear(2, 1)
    with torch.no_grad():
        live.weight.fill_(2.0)
    avg = DecoderAverage({"lin": live}, decay=0.75)
    expected = 2.0
    for v in [1.0, 5.0, -3.0]:
        with torch.no_grad():
            live.weight.fill_(v)
        avg.update({"lin": live})
        expected = 0.75 * expected + 0.25 * v
    assert torch.allclose(avg.averaged["lin"].weight, torch.full((1, 2), expected))
    assert not avg.averaged["lin"].weight.requires_grad
    assert float(live.weight.detach()[0, 0]) == -3.0  # the live weights are untouched


@pytest.mark.parametrize("decay", [-0.1, 1.0])
def test_a_decay_outside_0_1_is_refused(decay):
    with pytest.raises(ValueError, match="decay"):
        DecoderAverage({"lin": nn.Linear(2, 1)}, decay=decay)


def _model(decay: float, kind: str = "linear"):
    torch.manual_seed(0)
    model = build_model(model_node("segs", k=2, feature_dim=4, hidden=4, voxel_size=0.05, min_new_points=1,
                                   decoder_average=decay, appearance={"kind": kind, "dim": 3}))  # fmt: skip
    pts = torch.tensor([[0.0, 0.0, 2.0], [0.3, 0.1, 2.5], [-0.2, -0.1, 3.0]])
    model.add_points(pts, torch.rand(3, 3), torch.tensor([0, 0, 0]), None)
    model.register_views({0: torch.eye(4)})
    return model


def _view(kf_id=None):
    return View(torch.eye(4), Camera(fx=50.0, fy=50.0, cx=16.0, cy=12.0, width=32, height=24), kf_id)


def _train_steps(model, n: int):
    """n steps that move every decoder weight (a stand-in optimizer: the weights get noise)."""
    gen = torch.Generator().manual_seed(1)
    for _ in range(n):
        with torch.no_grad():
            for m in model.decoders().values():
                for p in m.parameters():
                    p.add_(torch.randn(p.shape, generator=gen) * 0.3)
        model.after_step()


@pytest.mark.parametrize("kind", ["linear", "ae"])
def test_renders_outside_training_decode_with_the_average_and_training_with_the_live_weights(kind):
    model = _model(0.9, kind)
    _train_steps(model, 5)
    view = _view(0)
    live, averaged = model.decode(view, 10), model.decode(view, 10, averaged=True)
    assert live.colors.shape != averaged.colors.shape or not torch.allclose(live.colors, averaged.colors)
    # the averaged decoding is the live decoding with the average's weights put in place
    with torch.no_grad():
        for name, m in model.decoders().items():
            for p, q in zip(m.parameters(), model.decoder_average.averaged[name].parameters()):
                p.copy_(q)
    swapped = model.decode(view, 10)
    for a, b in zip((averaged.means, averaged.scales, averaged.opacities, averaged.colors),
                    (swapped.means, swapped.scales, swapped.opacities, swapped.colors)):  # fmt: skip
        assert torch.allclose(a, b, atol=1e-6)
    # the export's decoding (every anchor; here all three are in view) is the averaged one too
    assert torch.allclose(model.decode_all(view).colors, averaged.colors, atol=1e-6)


def test_with_the_average_off_every_render_decodes_with_the_live_weights():
    model = _model(0.0)
    assert model.decoder_average is None
    _train_steps(model, 3)
    view = _view(0)
    assert torch.equal(model.decode(view, 10).colors, model.decode(view, 10, averaged=True).colors)


def test_the_average_is_not_counted_in_the_maps_size():
    on, off = _model(0.9), _model(0.0)
    assert on.counts()["params"] == off.counts()["params"]
    assert on.counts()["mb"] == off.counts()["mb"]


def test_a_checkpoint_without_the_average_restores_it_as_its_live_weights_and_one_with_it_loads_without():
    old = _model(0.0)
    _train_steps(old, 2)
    state = {"model." + k: v for k, v in old.state_dict().items()}
    new = _model(0.9)
    upgraded = new.upgrade_state(state, "model.")
    new.load_state_dict({k.removeprefix("model."): v for k, v in upgraded.items()})
    view = _view(0)
    assert torch.allclose(new.decode(view, 10, averaged=True).colors, old.decode(view, 10).colors, atol=1e-6)
    # and the other way: a checkpoint with an average loads into a model without one
    back = _model(0.0)
    state = {"model." + k: v for k, v in new.state_dict().items()}
    back.load_state_dict({k.removeprefix("model."): v for k, v in back.upgrade_state(state, "model.").items()})
    assert torch.equal(back.decode(view, 10).colors, old.decode(view, 10).colors)


def test_a_checkpoint_with_the_average_restores_it():
    model = _model(0.9)
    _train_steps(model, 4)
    state = {"model." + k: v for k, v in model.state_dict().items()}
    again = _model(0.9)
    again.load_state_dict({k.removeprefix("model."): v for k, v in again.upgrade_state(state, "model.").items()})
    view = _view(0)
    assert torch.equal(again.decode(view, 10, averaged=True).colors, model.decode(view, 10, averaged=True).colors)

