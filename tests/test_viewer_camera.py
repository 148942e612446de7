"""The viewer draws a map as seen from the browser's camera: the browser's pose read in viser's
convention, the Gaussians a render from that camera draws (a SEGS map decodes its Gaussians per
view), and a run shown from its checkpoint decoded again when the camera has moved and settled.
A tiny synthetic run (tests/conftest.py TINY); no browser (test_viewer.py has the one that needs it)."""
from __future__ import annotations

import shutil
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from conftest import TINY

viser = pytest.importorskip("viser", reason='the viewer extra is not installed (pip install -e ".[viewer]")')

from segs.data.frame import Camera  # noqa: E402
from segs.modules.scene_model import View  # noqa: E402
from segs.raster import EPS2D  # noqa: E402
from segs.viewer.scene import EVERY_ONE, SETTLE_S, BrowserCamera, Splats, browser_camera  # noqa: E402


@pytest.fixture(scope="module")
def cut_run(tmp_path_factory) -> Path:
    """A tiny training run shown from its checkpoint (no point_cloud.ply: as an interrupted run)."""
    out = tmp_path_factory.mktemp("camera") / "run"
    overrides = ["trainer.max_steps=300", "callbacks.periodic_checkpoint.every_n_steps=0", "eval.ply_fit_steps=0", f"hydra.run.dir={out}"]
    res = subprocess.run([sys.executable, "-m", "segs.train", *TINY, *overrides], capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-2000:]
    (out / "point_cloud.ply").unlink()
    return out


def test_the_browsers_pose_is_read_in_viser_convention():
    rng = np.random.default_rng(0)
    for _ in range(5):
        c2w = np.eye(4)
        c2w[:3, :3] = viser.transforms.SO3.exp(rng.normal(size=3)).as_matrix()
        c2w[:3, 3] = rng.normal(size=3)
        # what the server draws for a keyframe at c2w (server._draw_keyframes), read back
        wxyz = viser.transforms.SO3.from_matrix(c2w[:3, :3]).wxyz
        cam = browser_camera(wxyz, c2w[:3, 3], np.deg2rad(60.0), 800, 600, moved_at=5.0)
        np.testing.assert_allclose(cam.w2c, np.linalg.inv(c2w), atol=1e-9)
    assert cam.camera.fy == cam.camera.fx == pytest.approx(300.0 / np.tan(np.deg2rad(30.0)))
    assert (cam.camera.width, cam.camera.height, cam.camera.cx, cam.camera.cy, cam.moved_at) == (800, 600, 400.0, 300.0, 5.0)


def _test_views(run_dir: Path):
    from segs.view import load_mapper, load_sequence
    from segs.viewer.saved_run import read_run

    run = read_run(run_dir)
    mapper, (sequence, _) = load_mapper(run), load_sequence(run)
    test = [int(line.split(",")[0]) for line in (run_dir / "test_views.csv").read_text().splitlines()[1:]]
    return run, mapper, sequence, [(run.w2c_at(sequence.timestamps[i]), sequence[i]) for i in test]


def test_the_gaussians_for_a_camera_are_what_a_render_from_it_draws(cut_run):
    run, mapper, sequence, views = _test_views(cut_run)
    drawn = lambda c, w2c, cam: mapper.render_cloud((c.means, c.quats, c.scales, c.opacities, c.colors), w2c, cam).clamp(0, 1)  # noqa: E731
    for w2c, frame in views:  # the held-out frames
        cloud = mapper.gaussians(w2c, frame.camera)
        rendered, _ = mapper.render(View(torch.as_tensor(w2c, dtype=torch.float32), frame.camera), eps2d=EPS2D, averaged=True)
        torch.testing.assert_close(drawn(cloud, w2c, frame.camera), rendered.image.clamp(0, 1), atol=1e-4, rtol=0)
        # what the viewer drew before: every Gaussian decoded for the first keyframe, another image
        assert (drawn(mapper.gaussians(), w2c, frame.camera) - rendered.image.clamp(0, 1)).abs().mean() > 0.01
    assert len(views) >= 3


class _Browser:
    """A server with browsers whose cameras the test sets, client id -> camera (ViewerServer's
    browser_cameras / submit)."""

    def __init__(self):
        self.cameras: dict[int, BrowserCamera] = {}
        self.submitted = []

    def browser_cameras(self):
        return dict(self.cameras)

    def submit(self, snapshot):
        self.submitted.append(snapshot)


def _same(a: Splats, b: Splats) -> bool:
    return len(a) == len(b) and np.array_equal(a.means, b.means) and np.array_equal(a.colors, b.colors)


def test_a_run_shown_from_its_checkpoint_is_decoded_again_for_each_moved_camera(cut_run):
    from segs.view import CAMERA, CameraFollower

    run, mapper, sequence, views = _test_views(cut_run)
    server = _Browser()
    follow = CameraFollower(server, run, mapper, sequence, None)
    assert follow.fixed == CAMERA and follow.sources() == {} and not follow()  # no browser camera yet
    w2c, frame = views[0]
    server.cameras[7] = BrowserCamera(w2c, frame.camera, moved_at=time.time())
    assert not follow()  # still moving: not decoded at every frame of a drag
    server.cameras[7].moved_at -= SETTLE_S
    assert follow() and not follow()  # once, until it moves again
    shown = server.submitted[-1]
    assert shown.splats is None and set(shown.per_browser) == {7}  # the shared Gaussians unchanged, this browser's own
    assert _same(shown.per_browser[7], Splats.from_cloud(mapper.gaussians(w2c, frame.camera)).visible())
    # a second browser, elsewhere: decoded for it alone; the first keeps what it was sent
    w2c2, camera2 = views[-1][0], Camera(500.0, 500.0, 400.0, 300.0, 800, 600)
    server.cameras[8] = BrowserCamera(w2c2, camera2, moved_at=time.time() - SETTLE_S)
    assert follow() and not follow()
    second = server.submitted[-1]
    assert set(second.per_browser) == {8} and second.splats is None and second.splats_id != shown.splats_id
    assert _same(second.per_browser[8], Splats.from_cloud(mapper.gaussians(w2c2, camera2)).visible())
    assert not _same(second.per_browser[8], shown.per_browser[7])
    server.cameras[7] = BrowserCamera(w2c2, frame.camera, moved_at=time.time() - SETTLE_S)  # the first moves
    assert follow() and set(server.submitted[-1].per_browser) == {7}


def test_a_run_shown_from_its_ply_follows_the_camera_of_each_browser_that_chooses_it(cut_run, tmp_path):
    from segs.view import CAMERA, PLY, CameraFollower, load_mapper
    from segs.viewer.saved_run import read_run

    done = tmp_path / "done"
    shutil.copytree(cut_run, done)
    mapper = load_mapper(read_run(done))
    mapper.export_ply(done / "point_cloud.ply")  # newer than the checkpoint: the PLY is what is shown
    server = _Browser()
    views = _test_views(cut_run)[3]
    (w2c, frame), (w2c2, _) = views[0], views[-1]  # held-out frames' poses: the map in view
    server.cameras = {3: BrowserCamera(w2c, frame.camera, moved_at=time.time() - SETTLE_S),
                      4: BrowserCamera(w2c2, frame.camera, moved_at=time.time() - SETTLE_S)}  # fmt: skip
    follow = CameraFollower(server, read_run(done), mapper, None, None)  # no choice offered: the PLY for all
    assert not follow.choices and set(follow.sources().values()) == {PLY} and not follow() and not server.submitted
    server.choices = {3: PLY, 4: PLY}  # each browser's dropdown
    server.browser_choices = lambda: dict(server.choices)
    follow = CameraFollower(server, read_run(done), mapper, None, None, choices=True)
    assert not follow() and not server.submitted
    server.choices[3] = CAMERA  # browser 3 alone: its camera decoded for at once, browser 4 keeps the PLY
    assert follow() and not follow()
    switched = server.submitted[-1]
    assert switched.splats is None and set(switched.per_browser) == {3} and not switched.dropped
    assert _same(switched.per_browser[3], Splats.from_cloud(mapper.gaussians(w2c, frame.camera)).visible())
    server.cameras[3] = BrowserCamera(w2c2, frame.camera, moved_at=time.time() - SETTLE_S)  # 3 moves: decoded again
    server.cameras[4] = BrowserCamera(w2c, frame.camera, moved_at=time.time() - SETTLE_S)  # 4 moves: its PLY needs nothing
    assert follow() and set(server.submitted[-1].per_browser) == {3} and not follow()
    server.choices = {3: PLY, 4: CAMERA}  # both switch: 3 is shown the PLY again, 4 its own decoding
    assert follow() and not follow()
    back = server.submitted[-1]
    assert back.splats is None and back.dropped == {3} and set(back.per_browser) == {4}
    assert _same(back.per_browser[4], Splats.from_cloud(mapper.gaussians(w2c, frame.camera)).visible())
    del server.choices[4], server.cameras[4]  # 4 gone (the server drops its node): nothing to submit for it
    assert not follow() and follow.own == set() and len(server.submitted) == 3


class _Connected(_Browser):
    """The same browsers, `connected` of them (what LiveViewer asks of its server)."""

    connected = 1

    def clients(self) -> int:
        return self.connected

    def serve_selection(self, provider) -> bool:
        return False


class _Bridge:
    """What LiveViewer reads of the SLAM bridge: the run's trajectory (its test frames at their
    saved poses), test frames, keyframes, map points and speeds."""

    def __init__(self, run, sequence):
        test = [int(line.split(",")[0]) for line in (run.path / "test_views.csv").read_text().splitlines()[1:]]
        poses = {i: run.w2c_at(sequence.timestamps[i]) for i in test}
        self.map_points = _Points()
        self.run = SimpleNamespace(trajectory=lambda: poses, test_frames=lambda: test, keyframe_frames=dict, tracking_fps=lambda: None,
                                   mode="interleaved", dropped_frames=list)  # fmt: skip


class _Points:
    points = colors = np.zeros((0, 3), np.float32)

    def __len__(self) -> int:
        return 0


def test_training_takes_a_snapshot_for_a_moved_camera_before_its_period(cut_run):
    from segs.viewer.config import viewer_config
    from segs.viewer.live import LiveViewer

    run, mapper, sequence, views = _test_views(cut_run)
    cfg = viewer_config({"enabled": True, "host": "127.0.0.1", "port": None, "first_port": 18080, "refresh_s": 1000.0,
                         "max_share": 1.0, "test_views": 2})  # fmt: skip
    viewer = LiveViewer(cfg, sequence)
    viewer.server.close()
    viewer.server = server = _Connected()
    trainer = SimpleNamespace(global_step=10, max_steps=100, callbacks=[])
    step = lambda: viewer.on_train_batch_end(trainer, mapper, None, None, 0)  # noqa: E731
    viewer.on_train_start(trainer, mapper)
    viewer.bridge = _Bridge(run, sequence)
    renders = []
    render_image = mapper.render_image
    mapper.render_image = lambda *a, **k: renders.append(1) or render_image(*a, **k)  # the panel's test frames
    step()  # the first snapshot: no browser camera known yet
    first = server.submitted[0]
    assert len(server.submitted) == 1 and not first.per_browser and first.splats_label == EVERY_ONE
    assert _same(first.splats, Splats.from_cloud(mapper.gaussians()).visible())
    assert len(renders) == 1 and "1 held-out frames" in server.submitted[0].panel["test PSNR so far"]
    step()
    assert len(server.submitted) == 1  # refresh_s not over, the camera unknown
    w2c, frame = views[0]
    server.cameras[5] = BrowserCamera(w2c, frame.camera, moved_at=time.time())
    step()
    assert len(server.submitted) == 1  # moving
    server.cameras[5].moved_at -= SETTLE_S
    time.sleep(viewer.min_period())
    step()
    assert len(server.submitted) == 2
    shown = server.submitted[-1]
    assert shown.splats is None and set(shown.per_browser) == {5}  # this browser's own, the shared ones unchanged
    assert _same(shown.per_browser[5], Splats.from_cloud(mapper.gaussians(w2c, frame.camera)).visible())
    # no test frame rendered for a moved camera: the panel keeps the last one's PSNR
    assert len(renders) == 1 and shown.panel["test PSNR so far"] == server.submitted[0].panel["test PSNR so far"]
    assert len(viewer.snapshot_ms) == 2 and viewer.camera_ms == viewer.snapshot_ms[1:]
    step()
    assert len(server.submitted) == 2  # the same camera: back to refresh_s
    server.connected, w2c2 = 2, views[-1][0]
    server.cameras[6] = BrowserCamera(w2c2, frame.camera, moved_at=time.time() - SETTLE_S)  # a second browser
    time.sleep(viewer.min_period())
    step()
    assert len(server.submitted) == 3 and set(server.submitted[-1].per_browser) == {6}  # decoded for it alone
    viewer.refresh(trainer, mapper)  # a regular snapshot: every browser's camera, and no shared decoding (each has its own)
    regular = server.submitted[-1]
    assert set(regular.per_browser) == {5, 6} and regular.splats is None
    assert _same(regular.per_browser[6], Splats.from_cloud(mapper.gaussians(w2c2, frame.camera)).visible())
    server.connected = 3  # a third, without a camera yet: the shared Gaussians again
    viewer.refresh(trainer, mapper)
    assert set(server.submitted[-1].per_browser) == {5, 6} and _same(server.submitted[-1].splats, first.splats)


def test_browsers_at_the_same_camera_share_one_decoding(cut_run):
    from segs.viewer.scene import splats_for_each

    _, mapper, _, views = _test_views(cut_run)
    (w2c, frame), (w2c2, _) = views[0], views[-1]
    calls = []
    gaussians = mapper.gaussians
    mapper.gaussians = lambda *a, **k: calls.append(1) or gaussians(*a, **k)
    cameras = {1: BrowserCamera(w2c, frame.camera, 1.0), 2: BrowserCamera(w2c.copy(), frame.camera, 2.0),  # two tabs, one view
               3: BrowserCamera(w2c2, frame.camera, 1.0)}  # fmt: skip
    out = splats_for_each(mapper, cameras)
    assert len(calls) == 2 and out[1] is out[2] and _same(out[1], Splats.from_cloud(gaussians(w2c, frame.camera)).visible())
    assert _same(out[3], Splats.from_cloud(gaussians(w2c2, frame.camera)).visible()) and not _same(out[3], out[1])
