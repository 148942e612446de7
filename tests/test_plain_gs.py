"""Plain 3D-GS baseline: initialisation from points, densification edits Adam in place."""
from __future__ import annotations

import math

import torch

from segs.config import model_node
from segs.modules.config import build_model
from segs.modules.optim import make_adam


def _model():
    torch.manual_seed(0)
    densify = {"grad_threshold": 1e-3, "percent_dense": 0.01, "min_opacity": 0.05}
    m = build_model(model_node("plain_3dgs", sh_degree=1, densify=densify))
    m.scene_extent = 1.0
    xyz = torch.tensor([[0.0, 0, 2], [1.0, 0, 2], [0, 1.0, 2], [1.0, 1.0, 2]])
    m.add_points(xyz, torch.rand(4, 3), torch.tensor([0, 0, 1, 1]), None)
    return m


def test_points_initialise_gaussians_with_knn_scales():
    m = _model()
    assert len(m.gs) == 4
    # each point's 3 nearest neighbours are at 1, 1 and sqrt(2): scale = sqrt((1 + 1 + 2) / 3)
    assert torch.allclose(torch.exp(m.gs["log_scales"]), torch.full((4, 3), math.sqrt(4 / 3)), atol=1e-5)
    assert torch.allclose(torch.sigmoid(m.gs["opacities"]), torch.full((4, 1), 0.1))


def test_densify_clones_splits_prunes_and_keeps_moments():
    m = _model()
    opt = make_adam(m.param_groups())
    loss = sum((p**2).sum() for p in m.gs.parameters_by_name().values())
    loss.backward()
    opt.step()
    moments = {k: opt.state[p]["exp_avg"].clone() for k, p in m.gs.parameters_by_name().items()}
    with torch.no_grad():
        m.gs["log_scales"][0] = math.log(0.001)  # small -> clone
        m.gs["log_scales"][1] = math.log(0.5)  # large -> split
        m.gs["opacities"][2] = -10.0  # transparent -> pruned
    m.gs.grad_accum[:] = torch.tensor([1.0, 1.0, 0.0, 0.0])
    m.gs.grad_count[:] = 1.0
    out = m.densify.adjust(m.gs, opt, m.scene_extent, m.max_gaussians, prune_big=False)
    assert out == {"cloned": 1, "split": 1, "pruned": 2}  # the split parent and the transparent one
    assert len(m.gs) == 4 - 2 + 1 + 2
    for k, p in m.gs.parameters_by_name().items():
        state = opt.state[p]["exp_avg"]
        assert torch.equal(state[0], moments[k][0]) and torch.equal(state[1], moments[k][3]), k
        assert torch.equal(state[2:], torch.zeros_like(state[2:])), k
    assert torch.equal(m.gs.kf_tag, torch.tensor([0, 1, 0, 0, 0]))
    assert (m.gs.grad_accum == 0).all() and m.gs.max_radii.shape == (5,)  # statistics restart, rows aligned


def test_loop_correction_moves_only_the_tagged_gaussians():
    m = _model()
    T = torch.eye(4)
    T[:3, 3] = torch.tensor([0.5, 0.0, 0.0])
    before = m.gs["means"].detach().clone()
    assert m.correct_map({1: T}, None) == 2
    after = m.gs["means"].detach()
    assert torch.equal(after[:2], before[:2]) and torch.allclose(after[2:], before[2:] + T[:3, 3])


def test_an_opacity_reset_interval_of_zero_never_resets():
    for interval, resets in ((0, False), (100, True)):
        torch.manual_seed(0)
        m = build_model(model_node("plain_3dgs", densify={"opacity_reset_interval": interval, "from_step": 0}))
        m.scene_extent = 1.0
        m.add_points(torch.rand(8, 3) + torch.tensor([0.0, 0, 2]), torch.rand(8, 3), torch.zeros(8, dtype=torch.long), None)
        with torch.no_grad():
            m.gs["opacities"][:] = 2.0  # sigmoid 0.88: a reset caps it at 0.01
        opt = make_adam(m.param_groups())
        for step in range(1, 400):
            m.maintain(step, opt)
        assert bool((torch.sigmoid(m.gs["opacities"]) < 0.02).all()) is resets, interval
