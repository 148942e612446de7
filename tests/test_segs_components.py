"""Unit tests of the SEGS concepts: FPR, AfME, SEPM, decoding, growth / pruning, optimizer edits."""
import math

import pytest
import torch

from segs.config import model_node
from segs.data.frame import Camera
from segs.modules.afme import AppearanceEncoder, canonical_pose
from segs.modules.anchors import AnchorField
from segs.modules.config import build_model
from segs.modules.densification import AnchorGrowth
from segs.modules.fpr import fpr_loss, highpass_mask, lowpass_mask
from segs.modules.optim import make_adam
from segs.modules.scene_model import View
from segs.modules.sepm import voxelize


def test_fpr_zero_for_identical_images():
    img = torch.rand(24, 32, 3)
    for mode in ("high", "low", "low_high"):
        assert float(fpr_loss(img, img.clone(), scales=3, mode=mode)) == pytest.approx(0.0, abs=1e-6)


def test_fpr_hand_computed_delta_image():
    # A unit impulse has |F| = 1 at every frequency. 8x8: r = int(0.4*8/2) = 1, so the high-pass
    # mask zeroes the 2x2 centre: 60 of 64 entries of one of 3 channels differ by 1 from a black render.
    gt = torch.zeros(8, 8, 3)
    gt[0, 0, 1] = 1.0
    loss = fpr_loss(torch.zeros(8, 8, 3), gt, scales=1, mode="high")
    assert float(loss) == pytest.approx(60 / (3 * 64), rel=1e-6)
    # 4x4: r = 0, nothing masked -> 16 / 48
    gt4 = torch.zeros(4, 4, 3)
    gt4[0, 0, 0] = 1.0
    assert float(fpr_loss(torch.zeros(4, 4, 3), gt4, scales=1)) == pytest.approx(1 / 3, rel=1e-6)


def test_fpr_pyramid_weights_scales():
    gt, render = torch.rand(32, 32, 3), torch.rand(32, 32, 3)
    one = fpr_loss(render, gt, scales=1)
    two = fpr_loss(render, gt, scales=2)
    half = torch.nn.functional.interpolate(render.permute(2, 0, 1)[None], size=(16, 16), mode="bilinear")[0].permute(1, 2, 0)
    half_gt = torch.nn.functional.interpolate(gt.permute(2, 0, 1)[None], size=(16, 16), mode="bilinear")[0].permute(1, 2, 0)
    assert float(two) == pytest.approx(float(one) + 0.5 * float(fpr_loss(half, half_gt, scales=1)), rel=1e-5)


def test_highpass_mask_shape():
    m = highpass_mask(240, 320)
    r = int(0.4 * 240 / 2)  # 48
    assert m.shape == (240, 320)
    assert int((m == 0).sum()) == (2 * r) ** 2
    assert m[120, 160] == 0 and m[120 - r, 160 - r] == 0 and m[120 - r - 1, 160] == 1 and m[0, 0] == 1
    lp = lowpass_mask(240, 320)
    assert int(lp.sum()) == (2 * 24) ** 2


def test_afme_quaternion_sign_canonicalized():
    torch.manual_seed(0)
    enc = AppearanceEncoder("linear", dim=8)
    t, q = torch.randn(3), torch.nn.functional.normalize(torch.randn(4), dim=0)
    a, b = enc.embed(torch.cat([t, q])), enc.embed(torch.cat([t, -q]))
    assert torch.allclose(a, b)
    assert canonical_pose(t, -q)[3] >= 0


def test_afme_embedding_depends_on_pose_only_through_linear_layer():
    enc = AppearanceEncoder("linear", dim=4)
    w2c = torch.eye(4)
    w2c[:3, 3] = torch.tensor([0.1, 0.2, 0.3])
    out = enc(w2c, kf_id=None)
    expected = enc.net.weight @ torch.tensor([0.1, 0.2, 0.3, 1.0, 0.0, 0.0, 0.0]) + enc.net.bias
    assert torch.allclose(out, expected, atol=1e-6)


def test_ae_uses_nearest_training_view_for_unseen_frames():
    enc = AppearanceEncoder("ae", dim=2)
    with torch.no_grad():
        enc.table.weight[:2] = torch.tensor([[1.0, 0.0], [0.0, 1.0]])

    def pose(x):  # centre at (x,0,0)
        return torch.tensor([[1, 0, 0, -x], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])

    enc.register_view(7, View(pose(0.0), None).center)
    enc.register_view(9, View(pose(1.0), None).center)
    assert torch.equal(enc(pose(0.9), None), torch.tensor([0.0, 1.0]))
    assert torch.equal(enc(pose(0.9), 7), torch.tensor([1.0, 0.0]))


def test_sepm_voxelizes_and_skips_occupied_voxels():
    eps = 0.1
    pts = torch.tensor([[0.01, 0.0, 0.0], [0.02, 0.01, 0.0], [0.5, 0.5, 0.5], [1.04, 0.0, 0.0]])
    existing = torch.tensor([[1.0, 0.0, 0.0]])
    centres, index = voxelize(pts, eps, existing)
    got = sorted(tuple(round(v, 6) for v in c.tolist()) for c in centres)
    assert got == [(0.0, 0.0, 0.0), (0.5, 0.5, 0.5)]
    assert index[3] == -1 and index[0] == index[1] and index[0] >= 0
    again, _ = voxelize(pts, eps, torch.cat([existing, centres]))
    assert again.shape[0] == 0


def _camera():
    return Camera(fx=50.0, fy=50.0, cx=32.0, cy=24.0, width=64, height=48)


def _field(n=20, k=4, seed=0):
    torch.manual_seed(seed)
    field = AnchorField(k=k, feature_dim=8, hidden=8, appearance_dim=0, use_distance=False, frustum_margin=0.15)
    xyz = torch.rand(n, 3) * 2 - 1
    xyz[:, 2] += 4.0
    field.add(xyz, torch.randn(n, 8), torch.full((n, 6), math.log(0.05)), torch.arange(n), None)
    return field


def test_decoded_count_is_k_times_visible_minus_dropped():
    field = _field(n=30, k=5)
    with torch.no_grad():  # two anchors behind the camera are culled
        field.xyz[:2, 2] = -3.0
    decoded, info = field.decode(View(torch.eye(4), _camera()), None)
    assert info.visible.numel() == 28
    dropped = int((info.opacity <= 0).sum())
    assert len(decoded) == 5 * 28 - dropped
    assert (decoded.opacities > 0).all()
    assert 0 < dropped < 5 * 28  # random decoders drop some, not all


def _densifier_setup():
    field = _field(n=6, k=2)
    opt = make_adam(field.rows.groups({"features": 0.01, "offsets": 0.01, "log_scales": 0.01}))
    growth = AnchorGrowth(stats_from=0, grow_from=0, until=100, interval=10, scale_interval=False, grad_threshold=1e-3,
                          update_depth=3, init_factor=16, hierarchy_factor=4, min_opacity=0.005, success_threshold=0.8)  # fmt: skip
    return field, opt, growth


def _step_adam(field, opt):
    loss = sum((p**2).sum() for p in field.rows.parameters_by_name().values())
    loss.backward()
    opt.step()
    opt.zero_grad()


def test_growth_adds_anchors_only_in_empty_cells_and_keeps_moments():
    field, opt, dens = _densifier_setup()
    _step_adam(field, opt)
    feat = field.rows["features"]
    before = opt.state[feat]["exp_avg"].clone()
    with torch.no_grad():  # Gaussian 0 of anchor 0 sits 5 cm away; Gaussian 1 sits on anchor 1
        scale = torch.exp(field.rows["log_scales"][:, :3])
        field.rows["offsets"][0, 0] = torch.tensor([0.05, 0.0, 0.0]) / scale[0]
        field.rows["offsets"][1, 1] = 0.0
    field.rows.grad_accum[:] = 0.0
    field.rows.grad_visits[:] = 100.0
    field.rows.grad_accum[0, 0] = 1.0  # strong gradient
    field.rows.grad_accum[1, 1] = 1.0  # strong, but its cell already holds anchor 1
    gen = torch.Generator().manual_seed(0)
    out = dens.adjust(field, opt, interval=10, voxel_size=0.01, max_anchors=200_000, generator=gen)
    tags = field.rows.kf_tag
    assert out["grown"] >= 1 and len(field) == 6 + out["grown"]
    new = field.xyz[6:]
    target = field.xyz[0] + torch.tensor([0.05, 0.0, 0.0])
    assert (new - target).norm(dim=-1).min() < 0.16 * 1.8  # in the coarse cell around the Gaussian
    assert (new[:, None] - field.xyz[None, :6]).norm(dim=-1).min() > 1e-6  # never on an existing anchor
    assert torch.equal(tags[6:], torch.zeros(out["grown"], dtype=torch.long))  # inherits anchor 0's tag
    feat = field.rows["features"]
    assert torch.equal(opt.state[feat]["exp_avg"][:6], before)
    assert torch.equal(opt.state[feat]["exp_avg"][6:], torch.zeros_like(opt.state[feat]["exp_avg"][6:]))
    assert feat in opt.param_groups[0]["params"]


def test_pruning_removes_low_opacity_anchors_and_keeps_moments():
    field, opt, dens = _densifier_setup()
    _step_adam(field, opt)
    offsets = field.rows["offsets"]
    kept_state = opt.state[offsets]["exp_avg"][[0, 1, 3, 4, 5]].clone()
    field.rows.anchor_visits[:] = 50.0
    field.rows.opacity_accum[:] = 10.0
    field.rows.opacity_accum[2] = 0.01  # < 0.005 * 50
    xyz = field.xyz.clone()
    out = dens.adjust(field, opt, interval=10, voxel_size=0.01, max_anchors=200_000)
    tags = field.rows.kf_tag
    assert out["pruned"] == 1 and len(field) == 5
    assert torch.equal(field.xyz, xyz[[0, 1, 3, 4, 5]])
    assert torch.equal(tags, torch.tensor([0, 1, 3, 4, 5]))
    assert torch.equal(opt.state[field.rows["offsets"]]["exp_avg"], kept_state)
    assert (field.rows.anchor_visits == 0).all()  # statistics window restarted


def test_fused_decoders_equal_the_three_mlps():
    torch.manual_seed(1)
    field = AnchorField(k=3, feature_dim=8, hidden=8, appearance_dim=4, use_distance=False, frustum_margin=0.15)
    xyz = torch.rand(12, 3) - 0.5
    xyz[:, 2] += 3.0
    field.add(xyz, torch.randn(12, 8), torch.full((12, 6), math.log(0.1)), torch.zeros(12, dtype=torch.long), None)
    view, emb = View(torch.eye(4), _camera()), torch.randn(4)
    decoded, info = field.decode(view, emb)
    rel = field.xyz[info.visible] - view.center
    x = torch.cat([field.rows["features"][info.visible], rel / rel.norm(dim=-1, keepdim=True)], -1)
    opacity = torch.tanh(field.mlp_opacity(x)).reshape(-1)
    color = torch.sigmoid(field.mlp_color(torch.cat([x, emb.expand(len(x), 4)], -1))).reshape(-1, 3)
    cov = field.mlp_cov(x).reshape(-1, 7)
    keep = opacity > 0
    assert torch.allclose(decoded.opacities, opacity[keep], atol=1e-6)
    assert torch.allclose(decoded.colors, color[keep], atol=1e-6)
    assert torch.allclose(decoded.quats, torch.nn.functional.normalize(cov[keep, 3:7], dim=-1), atol=1e-6)
    scale = torch.exp(field.rows["log_scales"][info.visible]).repeat_interleave(3, 0)
    assert torch.allclose(decoded.scales, (scale[:, 3:] * torch.sigmoid(cov[:, :3]))[keep], atol=1e-6)
    means = field.xyz[info.visible].repeat_interleave(3, 0) + field.rows["offsets"][info.visible].reshape(-1, 3) * scale[:, :3]
    assert torch.allclose(decoded.means, means[keep], atol=1e-6)
    assert torch.equal(info.slots(3), torch.nonzero(keep).squeeze(1) + 0 * info.visible[0])  # all anchors visible here


def test_decode_gradients_equal_those_of_plain_indexing():
    torch.manual_seed(2)
    field = AnchorField(k=4, feature_dim=8, hidden=8, appearance_dim=0, use_distance=True, frustum_margin=0.15)
    xyz = torch.rand(30, 3) - 0.5
    xyz[:, 2] += 3.0
    xyz[:5, 2] = -3.0  # behind the camera: not visible
    field.add(xyz, torch.randn(30, 8), torch.randn(30, 6) * 0.3 - 2.0, torch.zeros(30, dtype=torch.long), None)
    field.rows["offsets"].data.normal_()
    view = View(torch.eye(4), _camera())
    decoded, info = field.decode(view, None)
    assert 0 < len(info.visible) < 30 and 0 < len(decoded) < 4 * len(info.visible)
    outs = (decoded.means, decoded.quats, decoded.scales, decoded.opacities, decoded.colors)
    weights = [torch.randn_like(t) for t in outs]
    loss = sum((t * w).sum() for t, w in zip(outs, weights))
    params = [field.rows["features"], field.rows["offsets"], field.rows["log_scales"], *field.mlp_cov.parameters()]
    got = torch.autograd.grad(loss, params)
    rows = {n: field.rows[n] for n in ("features", "offsets", "log_scales")}
    vis, keep, k = info.visible, info.keep, 4
    rel = field.xyz[vis] - view.center
    dist = rel.norm(dim=-1, keepdim=True)
    x = torch.cat([rows["features"][vis], rel / dist, dist], -1)
    scale = torch.exp(rows["log_scales"][vis])[keep // k]
    means = field.xyz[vis][keep // k] + rows["offsets"][vis].reshape(-1, 3)[keep] * scale[:, :3]
    cov = field.mlp_cov(x).reshape(-1, 7)[keep]
    plain = (means, torch.nn.functional.normalize(cov[:, 3:7], dim=-1), scale[:, 3:] * torch.sigmoid(cov[:, :3]),
             torch.tanh(field.mlp_opacity(x)).reshape(-1)[keep], torch.sigmoid(field.mlp_color(x)).reshape(-1, 3)[keep])  # fmt: skip
    for a, b in zip(plain, outs):
        assert torch.allclose(a, b, atol=1e-6)
    loss = sum((t * w).sum() for t, w in zip(plain, weights))
    want = torch.autograd.grad(loss, params)
    for g, w in zip(got, want):
        assert torch.allclose(g, w, atol=1e-5)
    assert got[0][~torch.isin(torch.arange(30), vis)].abs().sum() == 0  # no gradient for anchors out of view


def test_segs_model_sepm_batches_and_loop_correction():
    model = build_model(model_node("segs", k=2, feature_dim=4, hidden=4, voxel_size=0.05, min_new_points=3))
    pts = torch.tensor([[0.0, 0, 2], [0.01, 0, 2], [1.0, 0, 2]])
    assert model.add_points(pts, torch.rand(3, 3), torch.tensor([0, 0, 0]), None) == 2  # two voxels
    assert model.add_points(pts[:1] + 1.0, torch.rand(1, 3), torch.tensor([1]), None) == 0  # waits for 3 points
    added = model.add_points(torch.tensor([[2.0, 0, 2], [3.0, 0, 2]]), torch.rand(2, 3), torch.tensor([1, 1]), None)
    assert added == 3 and len(model.field) == 5
    assert torch.equal(model.field.rows.kf_tag, torch.tensor([0, 0, 1, 1, 1]))
    assert model.add_points(pts, torch.rand(3, 3), torch.tensor([2, 2, 2]), None) == 0  # voxels already held
    T = torch.eye(4)
    T[:3, :3] = torch.tensor([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]]) * 2.0  # rotation and scale 2
    before = model.field.xyz.clone()
    scales_before = torch.exp(model.field.rows["log_scales"].detach().clone())
    assert model.correct_map({1: T}, None) == 3
    assert torch.equal(model.field.xyz[:2], before[:2])
    assert torch.allclose(model.field.xyz[2:], before[2:] @ T[:3, :3].T)
    scales = torch.exp(model.field.rows["log_scales"].detach())
    assert torch.allclose(scales[2:], 2 * scales_before[2:]) and torch.equal(scales[:2], scales_before[:2])


def test_record_adds_the_screen_gradient_of_drawn_gaussians_only():
    from segs.modules.anchors import DecodeInfo

    field, _opt, dens = _densifier_setup()  # 6 anchors, k = 2
    field.rows.grad_accum[:] = 0.0
    field.rows.grad_visits[:] = 0.0
    info = DecodeInfo(visible=torch.tensor([1, 4]), keep=torch.tensor([0, 1, 3]), opacity=torch.ones(2, 2))
    grad = torch.tensor([[0.1, 0.0], [0.3, 0.4], [0.0, 0.2]])
    radii = torch.tensor([2, 0, 5], dtype=torch.int32)  # the second was not drawn
    dens.record(field, info, grad, radii, width=20, height=10)
    expected = torch.zeros(6, 2)
    expected[1, 0] = 0.1 * 10  # slot 2 (anchor 1, offset 0): |(0.1 * 20/2, 0)|
    expected[4, 1] = 0.2 * 5  # slot 9 (anchor 4, offset 1): |(0, 0.2 * 10/2)|
    assert torch.allclose(field.rows.grad_accum, expected)
    assert field.rows.grad_visits.sum() == 2 and field.rows.grad_visits[1, 0] == 1 and field.rows.grad_visits[4, 1] == 1


def test_afme_keeps_a_training_views_pose_vector_until_its_pose_object_changes():
    from segs.modules.afme import pose_vector

    enc = AppearanceEncoder("linear", dim=4)
    w2c = torch.eye(4)
    first = enc._kept(w2c, kf_id=7)[0]
    assert enc._kept(w2c, kf_id=7)[0] is first  # the same pose object: no conversion
    moved = torch.eye(4)
    moved[0, 3] = 0.5
    assert torch.equal(enc._kept(moved, kf_id=7)[0], pose_vector(moved))  # a replaced pose: converted again
    assert torch.equal(enc(moved, 7), enc.embed(pose_vector(moved)))
    assert enc._kept(w2c, kf_id=None)[0] is not first  # a novel view is not kept


@pytest.mark.parametrize("kind", ["linear", "mlp"])
def test_afme_of_a_view_equals_embed_of_its_pose_vector(kind):
    """forward embeds the kept input of a training view: the same values, bit for bit."""
    from segs.modules.afme import pose_vector

    torch.manual_seed(1)
    enc = AppearanceEncoder(kind, dim=4)
    enc.scene_extent = 2.5
    q, _ = torch.linalg.qr(torch.randn(3, 3))
    w2c = torch.eye(4)
    w2c[:3, :3], w2c[:3, 3] = q * torch.sign(torch.det(q)), torch.randn(3)
    assert torch.equal(enc(w2c, 3), enc.embed(pose_vector(w2c)))
    assert torch.equal(enc(w2c, 3), enc.embed(pose_vector(w2c)))  # the kept input


def test_no_growth_round_in_the_runs_last_interval():
    model = build_model(model_node("segs", total_steps=6750, k=2, feature_dim=4, hidden=4))
    rounds = []
    model.growth.adjust = lambda *a, **kw: rounds.append(1) or {"grown": 0, "pruned": 0, "anchors": 0}
    assert model._interval() == 100
    assert model.maintain(2600, None) != {} and len(rounds) == 1  # no run length known: the schedule's rounds
    model.run_steps = 2600  # a run stopped inside its 6,750-step schedule
    assert model.maintain(2500, None) != {} and len(rounds) == 2
    assert model.maintain(2600, None) == {} and len(rounds) == 2  # its new anchors would never be trained
    model.run_steps = 2650
    assert model.maintain(2600, None) == {} and model.maintain(2500, None) != {} and len(rounds) == 3
