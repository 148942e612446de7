"""segs.raster: cpu (C++) backend against the torch reference, edge cases, input checks, backends.

Gradient checks of the torch backend against finite differences, and of the C++ projection
against the PyTorch one, are in test_raster_grad.py.
"""
from __future__ import annotations

import math

import pytest
import torch

import segs.raster as raster
from segs.raster import BackendUnavailableError, _backends, _build, available_backends, rasterize
from segs.raster.scenes import Scene, random_scene

needs_cpu = pytest.mark.skipif("cpu" not in available_backends(), reason="C++ backend unavailable")
needs_cuda = pytest.mark.skipif(
    "cuda" not in available_backends(), reason="needs CUDA and gsplat (pip install 'segs[gpu]')"
)

@pytest.fixture(autouse=True)
def _one_torch_thread():
    """Small tensors: one thread is as fast and immune to a busy machine (OpenMP barriers)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


OUT_TOL = 1e-4  # max abs difference of image, depth, alpha
GRAD_TOL = 1e-3  # max abs difference of a gradient relative to its largest entry
BG = (0.3, 0.6, 0.9)


def small_scene(n, width=48, height=40, seed=0, scale=(0.03, 0.3), **kw) -> Scene:
    """A covered test image: Gaussians large enough for a few-dozen-pixel frame."""
    return random_scene(n, width, height, seed=seed, scale_range=scale, **kw)


def render_with_grads(scene: Scene, backend: str, background=None):
    """Render, back-propagate a loss that uses image, depth and alpha; return everything."""
    params = [p.detach().clone().requires_grad_(True) for p in scene.params()]
    dev = scene.means.device
    bg = None if background is None else torch.tensor(background, dtype=scene.means.dtype, device=dev)
    if bg is not None:
        bg.requires_grad_(True)
    r = rasterize(*params, scene.viewmat, scene.K, scene.width, scene.height,
                  background=bg, backend=backend)
    h, w = scene.height, scene.width
    weights = torch.linspace(0.5, 1.5, h * w * 3, dtype=r.image.dtype, device=dev).reshape(h, w, 3)
    loss = (r.image * weights).sum() + 0.3 * r.depth.sum() + 2.0 * (r.alpha * weights[..., 0]).sum()
    loss.backward()
    grads = {name: p.grad for name, p in zip(["means", "quats", "scales", "opacities", "colors"], params)}
    grads["means2d"] = r.means2d.grad
    if bg is not None:
        grads["background"] = bg.grad
    return r, grads


def assert_backends_agree(scene: Scene, background=None):
    a, ga = render_with_grads(scene, "cpu", background)
    b, gb = render_with_grads(scene, "torch", background)
    for name in ("image", "depth", "alpha"):
        diff = (getattr(a, name) - getattr(b, name)).abs().max().item()
        assert diff <= OUT_TOL, f"{name}: max abs diff {diff:.3g}"
    assert torch.equal(a.radii, b.radii)
    torch.testing.assert_close(a.means2d, b.means2d, rtol=1e-5, atol=1e-4)
    for name, ref in gb.items():
        got = ga[name]
        assert got is not None and ref is not None, name
        scale = ref.abs().max().item()
        err = (got - ref).abs().max().item()
        assert err <= GRAD_TOL * max(scale, 1e-12) + 1e-12, f"d/d{name}: {err:.3g} vs max {scale:.3g}"
    return a, b


# -- cpu vs torch -------------------------------------------------------------------------------
@needs_cpu
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_cpu_matches_torch_on_random_scenes(seed):
    a, _ = assert_backends_agree(small_scene(400, seed=seed), background=BG)
    assert a.alpha.mean() > 0.5  # a covered image, not an empty one


@needs_cpu
def test_cpu_threads_agree():
    """Tiles are shared out dynamically; the result must not depend on the thread count."""
    s = small_scene(3000, width=96, height=80, seed=12)
    a, ga = render_with_grads(s, "cpu", BG)
    torch.set_num_threads(2)
    b, gb = render_with_grads(s, "cpu", BG)
    assert torch.equal(a.image, b.image) and torch.equal(a.alpha, b.alpha)
    for name in ga:
        torch.testing.assert_close(ga[name], gb[name], rtol=1e-5, atol=1e-6 * ga[name].abs().max())


@needs_cpu
def test_cpu_matches_torch_on_a_saturated_scene():
    """Dense opaque Gaussians: pixels stop early (T < 1e-4) and alpha hits the 0.99 clamp."""
    s = small_scene(600, width=32, height=32, seed=3, scale=(0.1, 0.3))
    s.opacities = torch.full_like(s.opacities, 0.995)
    a, _ = assert_backends_agree(s)
    assert (a.alpha > 1 - 1e-3).float().mean() > 0.5


@needs_cpu
@pytest.mark.parametrize("size", [(37, 29), (80, 24), (16, 50), (1, 1)])
def test_cpu_matches_torch_on_odd_image_sizes(size):
    w, h = size
    assert_backends_agree(small_scene(200, width=w, height=h, seed=4))


@needs_cpu
def test_cpu_matches_torch_with_one_gaussian():
    s = small_scene(1, seed=5)
    s.means = torch.tensor([[0.0, 0.0, 3.0]]) @ s.viewmat[:3, :3] - s.viewmat[:3, 3] @ s.viewmat[:3, :3]
    a, _ = assert_backends_agree(s, background=BG)
    assert a.radii.item() > 0 and a.alpha.max() > 0.05


@needs_cpu
def test_cpu_matches_torch_with_huge_and_tiny_gaussians():
    s = small_scene(60, seed=6)
    s.scales[:20] = 3.0  # metres, right in front: cover the whole image
    s.scales[20:40] = 1e-6  # only the 0.3 px low-pass is left
    s.opacities[:20] = 0.2
    a, _ = assert_backends_agree(s, background=BG)
    assert a.radii[:20].min() > 48 and a.radii[20:40].max() <= 3


@needs_cpu
def test_cpu_matches_torch_with_zero_opacity():
    s = small_scene(100, seed=7)
    s.opacities.zero_()
    a, _ = assert_backends_agree(s, background=BG)
    torch.testing.assert_close(a.image, torch.tensor(BG).expand_as(a.image))
    assert a.alpha.abs().max() == 0


def _camera_points(s: Scene, points: torch.Tensor) -> torch.Tensor:
    """World positions of camera-frame points for the scene's viewmat."""
    R, t = s.viewmat[:3, :3], s.viewmat[:3, 3]
    return (points - t) @ R


@needs_cpu
def test_behind_camera_and_off_screen_are_culled():
    s = small_scene(120, seed=8)
    cam = torch.zeros(40, 3)
    cam[:10, 2] = -torch.linspace(0.5, 3, 10)  # behind
    cam[10:15, 2] = 0.0  # in the camera centre plane (division by zero if not guarded)
    cam[15:20, 2] = 0.005  # in front but closer than near = 0.01
    cam[20:30] = torch.tensor([50.0, 0.0, 3.0])  # far off to the right
    cam[30:40] = torch.tensor([0.0, -40.0, 2.0])  # far above
    s.means[:40] = _camera_points(s, cam)
    a, _ = assert_backends_agree(s)
    assert (a.radii[:40] == 0).all() and (a.radii[40:] > 0).any()
    assert torch.isfinite(a.means2d).all()


@needs_cpu
def test_cpu_matches_torch_far_plane_and_grazing_gaussians():
    """Gaussians beyond `far`, and some just outside the field of view (Jacobian clamp)."""
    s = small_scene(150, seed=9)
    cam = torch.tensor([[0.0, 0.0, 150.0], [1.9, 0.2, 2.0], [-1.8, -1.2, 2.5], [0.0, 1.6, 2.0]])
    s.means[:4] = _camera_points(s, cam)
    s.scales[1:4] = 0.4
    a, _ = assert_backends_agree(s)
    assert a.radii[0] == 0


@needs_cpu
def test_float64_inputs_run_on_cpu_backend():
    s = small_scene(100, seed=10, dtype=torch.float64)
    r = rasterize(*s.params(), s.viewmat, s.K, s.width, s.height, backend="cpu")
    ref = rasterize(*s.params(), s.viewmat, s.K, s.width, s.height, backend="torch")
    assert r.image.dtype == torch.float64
    assert (r.image - ref.image).abs().max() < OUT_TOL


# -- N = 0 --------------------------------------------------------------------------------------
@pytest.mark.parametrize("backend", ["torch", pytest.param("cpu", marks=needs_cpu)])
def test_no_gaussians_renders_the_background(backend):
    s = small_scene(0, width=20, height=10)
    bg = torch.tensor(BG, requires_grad=True)
    params = [p.requires_grad_(True) for p in s.params()]
    r = rasterize(*params, s.viewmat, s.K, 20, 10, background=bg, backend=backend)
    assert r.image.shape == (10, 20, 3) and r.depth.shape == (10, 20) and r.alpha.shape == (10, 20)
    assert r.means2d.shape == (0, 2) and r.radii.shape == (0,)
    torch.testing.assert_close(r.image, torch.tensor(BG).expand(10, 20, 3))
    assert r.alpha.abs().max() == 0 and r.depth.abs().max() == 0
    r.image.sum().backward()
    torch.testing.assert_close(bg.grad, torch.full((3,), 200.0))


# -- semantics ----------------------------------------------------------------------------------
@pytest.mark.parametrize("backend,eps2d", [("torch", None), ("torch", 0.0), ("torch", 1.2),
                                           pytest.param("cpu", 1.2, marks=needs_cpu)])
def test_single_isotropic_gaussian_projects_like_a_pinhole(backend, eps2d):
    K = torch.tensor([[100.0, 0, 30], [0, 100.0, 20], [0, 0, 1]])
    viewmat = torch.eye(4)
    viewmat[:3, 3] = torch.tensor([0.0, 0.0, 1.5])  # camera 1.5 m behind the world origin
    means, quats = torch.tensor([[0.0, 0.0, 0.5]]), torch.tensor([[1.0, 0, 0, 0]])
    scales, op, col = torch.full((1, 3), 0.04), torch.tensor([0.8]), torch.tensor([[1.0, 0.5, 0.0]])
    low_pass = {} if eps2d is None else {"eps2d": eps2d}
    r = rasterize(means, quats, scales, op, col, viewmat, K, 64, 48, backend=backend, **low_pass)
    torch.testing.assert_close(r.means2d, torch.tensor([[30.0, 20.0]]))
    sigma2 = (100 * 0.04 / 2.0) ** 2 + (0.3 if eps2d is None else eps2d)  # EWA variance (px^2) plus the low-pass
    assert r.radii.item() == math.ceil(3 * math.sqrt(sigma2 + math.sqrt(0.1)))  # 3D-GS's eigenvalue floor
    y, x = 20, 30  # pixel (x, y) has centre (x + .5, y + .5)
    expected = 0.8 * math.exp(-0.5 * (0.25 + 0.25) / sigma2)
    assert abs(r.alpha[y, x].item() - expected) < 1e-5
    assert abs(r.depth[y, x].item() - 2.0) < 1e-5
    torch.testing.assert_close(r.image[y, x], torch.tensor([1.0, 0.5, 0.0]) * expected)


def test_front_to_back_order_and_expected_depth():
    """Two Gaussians on one ray: the nearer one occludes; depth is the alpha-weighted mean z."""
    K = torch.tensor([[50.0, 0, 8], [0, 50.0, 8], [0, 0, 1]])
    means = torch.tensor([[0.0, 0.0, 4.0], [0.0, 0.0, 2.0]])  # listed far first
    quats = torch.tensor([[1.0, 0, 0, 0]] * 2)
    scales = torch.full((2, 3), 0.5)
    r = rasterize(means, quats, scales, torch.tensor([0.5, 0.5]),
                  torch.tensor([[0.0, 0, 1], [1.0, 0, 0]]), torch.eye(4), K, 16, 16, backend="torch")
    a1 = 0.5 * math.exp(-0.5 * 0.5 / ((50 * 0.5 / 2) ** 2 + 0.3))  # near one at pixel (8,8)
    a2 = 0.5 * math.exp(-0.5 * 0.5 / ((50 * 0.5 / 4) ** 2 + 0.3))
    w1, w2 = a1, a2 * (1 - a1)
    torch.testing.assert_close(r.image[8, 8], torch.tensor([w1, 0.0, w2]), atol=1e-6, rtol=1e-5)
    assert abs(r.alpha[8, 8].item() - (w1 + w2)) < 1e-6
    assert abs(r.depth[8, 8].item() - (2 * w1 + 4 * w2) / (w1 + w2)) < 1e-5


# -- input checks -------------------------------------------------------------------------------
def _args(n=5):
    s = small_scene(n, width=16, height=16)
    return dict(means=s.means, quats=s.quats, scales=s.scales, opacities=s.opacities,
                colors=s.colors, viewmat=s.viewmat, K=s.K, width=16, height=16)


@pytest.mark.parametrize(
    "name, value, words",
    [
        ("means", torch.zeros(5, 2), ["means", "[5, 2]", "[N, 3]"]),
        ("quats", torch.zeros(5, 3), ["quats", "[5, 3]", "[N, 4]"]),
        ("scales", torch.zeros(4, 3), ["scales", "[4, 3]", "N=5"]),
        ("opacities", torch.zeros(5, 1), ["opacities", "[5, 1]", "[N]"]),
        ("colors", torch.zeros(5, 3, dtype=torch.int64), ["colors", "int64", "float32"]),
        ("colors", torch.zeros(5, 3, dtype=torch.float64), ["colors", "float64", "like means"]),
        ("viewmat", torch.eye(3), ["viewmat", "[3, 3]", "[4, 4]"]),
        ("K", torch.zeros(3, 3), ["K", "focal"]),
        ("width", 0, ["width", "positive int"]),
        ("height", 2.5, ["height", "positive int"]),
        ("means", [[0.0, 0.0, 1.0]] * 5, ["means", "tensor", "list"]),
    ],
)
def test_bad_input_is_a_value_error_naming_the_argument(name, value, words):
    args = _args()
    args[name] = value
    with pytest.raises(ValueError) as info:
        rasterize(**args, backend="torch")
    for w in words:
        assert w in str(info.value), (w, str(info.value))


@pytest.mark.parametrize("eps2d", [-0.1, float("nan"), float("inf")])
def test_a_low_pass_that_is_not_a_finite_non_negative_number_is_refused(eps2d):
    with pytest.raises(ValueError, match="eps2d"):
        rasterize(**_args(), backend="torch", eps2d=eps2d)


def test_non_finite_values_are_rejected():
    for name in ("means", "quats", "scales", "opacities", "colors", "viewmat", "K"):
        args = _args()
        args[name] = args[name].clone()
        args[name].view(-1)[0] = float("nan") if name != "scales" else float("inf")
        with pytest.raises(ValueError, match=f"^{name}: 1 non-finite"):
            rasterize(**args, backend="torch")


def test_check_values_false_skips_only_the_read_of_the_values():
    """The values' read (a wait on a GPU) is skipped; shapes, dtypes and devices are still checked."""
    args = _args()
    args["colors"] = args["colors"].clone()
    args["colors"][0, 0] = float("nan")
    out = rasterize(**args, backend="torch", check_values=False)
    assert out.image.shape == (args["height"], args["width"], 3)
    args["quats"] = args["quats"][:, :3]
    with pytest.raises(ValueError, match="quats: expected shape"):
        rasterize(**args, backend="torch", check_values=False)


def test_bad_background_device_and_planes():
    args = _args()
    with pytest.raises(ValueError, match=r"background: expected shape \[3\]"):
        rasterize(**args, background=torch.zeros(4), backend="torch")
    with pytest.raises(ValueError, match="near, far"):
        rasterize(**args, near=2.0, far=1.0, backend="torch")
    args["colors"] = args["colors"].to("meta")
    with pytest.raises(ValueError, match="colors: expected device cpu"):
        rasterize(**args, backend="torch")


# -- backends -----------------------------------------------------------------------------------
def test_available_backends_lists_what_runs_here():
    names = available_backends()
    assert "torch" in names
    assert ("cuda" in names) == (raster._cuda_backend.unavailable_reason() is None)


def test_unknown_backend_is_a_value_error():
    with pytest.raises(ValueError, match="backend: expected one of"):
        rasterize(**_args(), backend="opengl")


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the message without CUDA")
def test_cuda_without_cuda_says_why_and_what_is_available():
    with pytest.raises(BackendUnavailableError) as info:
        rasterize(**_args(), backend="cuda")
    msg = str(info.value)
    assert "cuda" in msg and "torch" in msg and "Available" in msg


def test_missing_cpu_backend_falls_back_to_torch_once(monkeypatch):
    monkeypatch.setenv("SEGS_RASTER_NO_CPU", "1")
    monkeypatch.setattr(_backends, "_warned", set())
    with pytest.warns(RuntimeWarning, match="SEGS_RASTER_NO_CPU"):
        r = rasterize(**_args(), backend="auto")
    assert r.backend == "torch"
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rasterize(**_args(), backend="auto")  # no second warning
    with pytest.raises(BackendUnavailableError, match="SEGS_RASTER_NO_CPU.*'torch'"):
        rasterize(**_args(), backend="cpu")


def test_missing_compiler_is_reported(monkeypatch, tmp_path):
    monkeypatch.setenv("CXX", "no-such-compiler-xyz")
    with pytest.raises(_build.BuildError, match="no C\\+\\+ compiler.*no-such-compiler-xyz"):
        _build._compile("segs_raster_cpu_test", tmp_path)


@needs_cpu
def test_auto_picks_cpu_for_cpu_tensors():
    assert rasterize(**_args(), backend="auto").backend == "cpu"


# -- cuda (gsplat) ------------------------------------------------------------------------------
@needs_cuda
def test_cuda_matches_torch():
    """gsplat clamps alpha at 0.999 and bounds Gaussians its own way: compare loosely."""
    s = small_scene(400, width=64, height=48, seed=11)
    s.opacities = s.opacities.clamp(max=0.9)
    a, ga = render_with_grads(
        Scene(*[t.cuda() for t in s.params()], s.viewmat.cuda(), s.K.cuda(), 64, 48), "cuda", BG
    )
    b, gb = render_with_grads(s, "torch", BG)
    assert (a.image.cpu() - b.image).abs().mean() < 2e-3
    assert (a.alpha.cpu() - b.alpha).abs().mean() < 2e-3
    mask = b.alpha > 0.5
    assert (a.depth.cpu() - b.depth)[mask].abs().mean() < 1e-2
    for name in ("colors", "opacities", "means2d"):
        cos = torch.nn.functional.cosine_similarity(ga[name].cpu().flatten(), gb[name].flatten(), dim=0)
        assert cos > 0.99, (name, cos)
