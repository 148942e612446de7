"""The web viewer (segs.viewer, python -m segs.view): the scene it serves for a train and a track
run, its bad-input answers, and a real browser (headless Chromium through playwright) watching
the map of a training run grow. Tiny synthetic runs (tests/conftest.py TINY)."""
from __future__ import annotations

import io
import os
import re
import shutil
import socket
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from plyfile import PlyData

from conftest import TINY
from segs.config import compose
from segs.errors import ConfigError, DataError

viser = pytest.importorskip("viser", reason='the viewer extra is not installed (pip install -e ".[viewer]")')

from segs.viewer.saved_run import read_gaussian_ply, read_run  # noqa: E402
from segs.viewer.scene import MIN_OPACITY, Splats  # noqa: E402
from segs.viewer.server import choose_port  # noqa: E402

CHROMIUM = Path("/usr/bin/chromium")
BROWSER_ARGS = ["--headless=new", "--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
                "--disable-sync", "--no-first-run", "--disable-dev-shm-usage"]  # fmt: skip


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _run(module: str, out: Path, *overrides: str) -> Path:
    """A tiny run of `python -m module` (segs.train / segs.track) in the folder out."""
    res = subprocess.run([sys.executable, "-m", module, *TINY, *overrides, f"hydra.run.dir={out}"], capture_output=True, text=True,
                         timeout=600)  # fmt: skip
    assert res.returncode == 0, res.stderr[-2000:]
    return out


@pytest.fixture(scope="module")
def train_run(tmp_path_factory) -> Path:
    """A finished tiny training run (metrics.json, final.ckpt, point_cloud.ply, map_points.ply)."""
    return _run("segs.train", tmp_path_factory.mktemp("train") / "run", "callbacks.periodic_checkpoint.every_n_steps=0")


@pytest.fixture(scope="module")
def track_run(tmp_path_factory) -> Path:
    """A finished tiny tracking-only run (trajectory.txt, keyframes.txt, map_points.ply, tracking.json)."""
    return _run("segs.track", tmp_path_factory.mktemp("track") / "run")


def _serve(run_dir: Path):
    from segs.view import serve

    server, provider, follow = serve(run_dir, "127.0.0.1", None, _free_port())
    assert server.wait_idle(timeout=30)
    return server, provider, follow


@pytest.mark.parametrize("overrides, message", [
    (["+viewer.port=9000"], "viewer.port: set while the viewer is off; add viewer=on"),
    (["viewer=on", "+viewer.colour=red"], "viewer.colour: unknown key"),
    (["viewer=on", "viewer.refresh_s=0"], "viewer.refresh_s=0.0 is out of range"),
    (["viewer=on", "viewer.port=70000"], "viewer.port=70000 is out of range"),
    (["viewer=on", "viewer.max_share=0"], "viewer.max_share=0.0 is out of range"),
])  # fmt: skip
def test_a_bad_viewer_key_is_one_line_naming_it(overrides, message):
    from segs.config import validate

    with pytest.raises(ConfigError, match=re.escape(message)):
        validate(compose(TINY + overrides), mapper=False)


def test_a_busy_port_is_skipped_or_refused_when_given():
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        taken, note = choose_port("127.0.0.1", None, port)
        assert taken != port and str(port) in note and str(taken) in note
        with pytest.raises(ConfigError, match=f"port {port} on 127.0.0.1 is busy"):
            choose_port("127.0.0.1", port, 8080)


def test_the_server_serves_a_train_run(train_run):
    run = read_run(train_run)
    assert run.kind == "train" and run.status == "finished" and run.checkpoint.name == "final.ckpt"
    server, provider, follow = _serve(train_run)
    try:
        page = urllib.request.urlopen(server.url, timeout=10).read().decode()
        assert "<html" in page.lower()
        splats = server.nodes["/map/gaussians"]
        logits = np.asarray(PlyData.read(str(train_run / "point_cloud.ply"))["vertex"]["opacity"], np.float64)
        n_visible = int((1.0 / (1.0 + np.exp(-logits)) >= MIN_OPACITY).sum())
        # the exported Gaussians (fitted to the views: none is below what can show), the map decoded
        # for the browser's camera one choice away
        assert len(splats.buffer) == n_visible == len(logits) > 0
        assert follow.choices and follow.fixed == "point_cloud.ply (as a 3D-GS viewer shows it)"
        assert len(server.nodes["/map/points"].points) == len(PlyData.read(str(train_run / "map_points.ply"))["vertex"]) > 0
        assert {"/trajectory/estimated", "/trajectory/ground_truth"} <= set(server.nodes)
        frustums = [k for k in server.nodes if k.startswith("/keyframes/")]
        assert len(frustums) >= 3
        kf_id = int(frustums[0].rsplit("_", 1)[1])
        server.selections.put((12345, kf_id))  # selected in a browser gone since: nothing to answer
        assert not server.serve_selection(provider) and server.selections.empty()
        image, render, note = provider(kf_id)
        assert render is not None and render.shape == image.shape and f"keyframe {kf_id}" in note
        assert render.std() > 1  # a render of the map, not a blank image
    finally:
        server.close()


def test_the_server_serves_a_track_run_with_its_map_points(track_run):
    run = read_run(track_run)
    assert run.kind == "track" and run.status == "finished" and len(run.keyframes) >= 3
    points = PlyData.read(str(track_run / "map_points.ply"))["vertex"]
    assert len(points) > 0 and {"x", "y", "z", "red", "green", "blue", "kf_id"} <= set(points.data.dtype.names)
    server, provider, follow = _serve(track_run)
    try:
        assert "/map/gaussians" not in server.nodes and not follow.choices  # tracking only: no Gaussians
        assert len(server.nodes["/map/points"].points) == len(points)
        assert "/trajectory/estimated" in server.nodes
        assert len([k for k in server.nodes if k.startswith("/keyframes/")]) == len(run.keyframes)
        image, render, note = provider(run.keyframes[0][0])
        assert render is None and image.ndim == 3 and "tracking only" in note
    finally:
        server.close()


def test_an_interrupted_train_run_is_shown_from_its_last_checkpoint(train_run, tmp_path):
    cut = tmp_path / "cut"
    shutil.copytree(train_run, cut)
    (cut / "metrics.json").unlink()
    (cut / "checkpoints" / "final.ckpt").rename(cut / "checkpoints" / "last.ckpt")
    (cut / "trajectory.txt").rename(cut / "trajectory_partial.txt")
    (cut / "point_cloud.ply").unlink()
    run = read_run(cut)
    assert run.status == "interrupted" and run.checkpoint.name == "last.ckpt" and run.trajectory is not None
    server, _, follow = _serve(cut)
    try:
        assert "/map/gaussians" in server.nodes and "/trajectory/estimated" in server.nodes and not follow.choices
        from_checkpoint = len(server.nodes["/map/gaussians"].buffer)
    finally:
        server.close()
    # a PLY older than the checkpoint (a resumed run stopped again) is not what the map is now
    from segs.view import load_mapper, snapshot

    shutil.copy(train_run / "point_cloud.ply", cut / "point_cloud.ply")
    os.utime(cut / "point_cloud.ply", (1.0, 1.0))
    run = read_run(cut)
    mapper = load_mapper(run)
    shown, decoded = snapshot(run, mapper, None, None).splats, Splats.from_cloud(mapper.gaussians()).visible()
    exported = read_gaussian_ply(cut / "point_cloud.ply").visible()
    assert len(shown) == from_checkpoint == len(decoded) and np.array_equal(shown.colors, decoded.colors)
    assert len(exported) != len(shown) or not np.allclose(exported.colors, shown.colors, atol=1e-3)
    os.utime(cut / "point_cloud.ply")  # newer than the checkpoint: the PLY is shown
    assert np.array_equal(snapshot(read_run(cut), mapper, None, None).splats.colors, exported.colors)


@pytest.mark.slow
def test_a_folder_that_is_not_a_run_is_one_line_and_exit_2(tmp_path):
    with pytest.raises(DataError, match="not a run folder"):
        read_run(tmp_path)
    res = subprocess.run([sys.executable, "-m", "segs.view", str(tmp_path)], capture_output=True, text=True, timeout=120)
    assert res.returncode == 2, res.stderr
    assert res.stderr.strip().count("\n") == 0 and "not a run folder" in res.stderr


@pytest.mark.slow
def test_a_given_busy_port_is_one_line_and_exit_2(track_run):
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        res = subprocess.run([sys.executable, "-m", "segs.view", str(track_run), "--port", str(port)], capture_output=True,
                             text=True, timeout=120)  # fmt: skip
    assert res.returncode == 2, res.stderr
    assert res.stderr.strip().count("\n") == 0 and f"port {port}" in res.stderr and "busy" in res.stderr


# -- a real browser -------------------------------------------------------------------------------
def _browser_or_skip():
    playwright = pytest.importorskip("playwright.sync_api", reason="playwright is not installed (pip install playwright)")
    if not CHROMIUM.is_file():
        pytest.skip(f"no browser: {CHROMIUM} is missing (Debian: apt-get install chromium)")
    return playwright


def _pixels(png: bytes) -> np.ndarray:
    """The canvas part of a screenshot that the panel and the notices never cover: [h,w,3] float."""
    from PIL import Image

    image = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.float64)
    h, w = image.shape[:2]
    return image[int(0.2 * h): int(0.9 * h), int(0.06 * w): int(0.6 * w)]


@pytest.mark.slow
def test_a_browser_shows_the_map_growing_during_training(tmp_path):
    sync = _browser_or_skip()
    import lightning as L
    
    from segs.train import build, step_batches
    from segs.viewer.live import LiveViewer

    steps, stops = 60, (15, 60)
    overrides = [f"trainer.max_steps={steps}", "callbacks.periodic_checkpoint.every_n_steps=0", "eval.enabled=false", "viewer=on",
                 f"viewer.first_port={_free_port()}", "viewer.refresh_s=1000"]  # fmt: skip
    cfg = compose(TINY + overrides, output_dir=str(tmp_path / "run"))
    t = build(cfg)
    module, trainer = t.module, t.trainer
    viewer = next(c for c in trainer.callbacks if isinstance(c, LiveViewer))
    reached = {s: threading.Event() for s in stops}
    go_on = {s: threading.Event() for s in stops}
    seen: dict[int, int] = {}

    class PauseAt(L.Callback):
        """At each stop: a snapshot (on the training thread, as the viewer takes them), then wait."""

        def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
            step = trainer.global_step
            if step in reached:
                viewer.refresh(trainer, pl_module)
                seen[step] = pl_module.counts().gaussians
                reached[step].set()
                go_on[step].wait(timeout=120)

    trainer.callbacks.append(PauseAt())
    fit = threading.Thread(target=trainer.fit, args=(module, step_batches(steps)), daemon=True)
    shots = {}
    try:
        with sync.sync_playwright() as p:
            # launch() gives the browser a fresh temporary profile (user data dir) of its own
            browser = p.chromium.launch(executable_path=str(CHROMIUM), args=BROWSER_ARGS)
            page = browser.new_page(viewport={"width": 1000, "height": 700})
            page.goto(viewer.server.url)
            page.wait_for_selector("canvas", timeout=60_000)
            page.wait_for_timeout(1000)
            blank = _pixels(page.screenshot())  # connected, nothing mapped yet
            fit.start()
            for step in stops:
                assert reached[step].wait(timeout=120), f"training did not reach step {step}"
                assert viewer.server.wait_idle(timeout=60)
                page.get_by_text(f"{step} of {steps}").wait_for(timeout=60_000)
                page.wait_for_timeout(2500)  # the splats are sorted and drawn by the page after they arrive
                shots[step] = _pixels(page.screenshot())
                text = page.inner_text("body")
                assert f"Gaussians\t{seen[step]}\n" in text or f"Gaussians {seen[step]}" in " ".join(text.split()), text
                if step == stops[-1]:  # the browser's camera, where the first snapshot put it, read back
                    framed, c2w = viewer.server.framed, None
                    for _ in range(100):  # the browser may still report its camera from before the framing
                        c2w = np.linalg.inv(next(iter(viewer.server.browser_cameras().values())).w2c)
                        if np.allclose(c2w[:3, 3], framed.position, atol=1e-3 * framed.extent):
                            break
                        time.sleep(0.2)
                    forward = framed.look_at - framed.position
                    np.testing.assert_allclose(c2w[:3, 3], framed.position, atol=1e-3 * framed.extent)
                    assert c2w[:3, 2] @ forward / np.linalg.norm(forward) > 0.999
                    assert "decoded for this camera's view" in " ".join(text.split())
                go_on[step].set()
            browser.close()
    finally:
        for e in go_on.values():
            e.set()
        if fit.ident is not None:
            fit.join(timeout=120)
    first, last = shots[stops[0]], shots[stops[1]]
    assert blank.var() < 50, "the canvas is not blank before the first snapshot"
    assert first.var() > 100 and last.var() > 100, (first.var(), last.var())  # the map is drawn
    assert np.abs(first - last).mean() > 1.0  # and it changed between the two steps


def _until(what, timeout: float = 60.0, every=None):
    """Wait for what() to be true (calling every() between tries); what's last value."""
    end = time.time() + timeout
    while not (value := what()) and time.time() < end:
        if every is not None:
            every()
        time.sleep(0.1)
    return value


def _open_pages(browser, server, n: int) -> tuple[list, list[int]]:
    """n pages of the server's viewer opened one after the other: (pages, their client ids)."""
    pages, ids = [], []
    for _ in range(n):
        pages.append(browser.new_page(viewport={"width": 900, "height": 640}))
        pages[-1].goto(server.url)
        pages[-1].wait_for_selector("canvas", timeout=60_000)
        assert _until(lambda: len(server.server.get_clients()) == len(pages))
        ids.append(max(set(server.server.get_clients()) - set(ids)))
    return pages, ids


def _decoded_as_they_are(server, follow) -> dict:
    """The browsers' cameras (client id -> BrowserCamera) once none has moved for 1 s and the
    Gaussians drawn for each browser at CAMERA were decoded for its camera as it is now (a camera
    that moved late in the quiet second is not settled yet: it is waited for, not read)."""

    def still():
        if _until(follow, timeout=1.0) or not server.wait_idle(5):
            return None
        cameras = server.browser_cameras()
        current = all(follow.decoded.moved_at.get(cid) == cameras[cid].moved_at for cid in follow.own if cid in cameras)
        return cameras if current else None

    cameras = _until(still, timeout=60)
    assert cameras, (server.browser_cameras(), follow.decoded.moved_at)
    return cameras


def _point(camera, c2w: np.ndarray) -> None:
    """Put a browser's camera (viser's client camera) at c2w [4,4] (OpenCV axes)."""
    camera.up_direction = tuple(-c2w[:3, 1])
    camera.position, camera.look_at = tuple(c2w[:3, 3]), tuple(c2w[:3, 3] + c2w[:3, 2])


@pytest.mark.slow
def test_two_browsers_each_see_the_map_decoded_for_their_own_camera(train_run, tmp_path):
    sync = _browser_or_skip()
    from segs.view import load_mapper
    from segs.viewer.scene import OWN, splats_for

    cut = tmp_path / "cut"
    shutil.copytree(train_run, cut)
    (cut / "point_cloud.ply").unlink()  # shown from its checkpoint, decoded for each browser's camera
    server, provider, follow = _serve(cut)
    mapper = load_mapper(read_run(cut))
    views = [np.linalg.inv(v.w2c.numpy().astype(np.float64)) for v in mapper.training_views()]
    try:
        with sync.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=str(CHROMIUM), args=BROWSER_ARGS)
            pages, ids = _open_pages(browser, server, 2)
            clients = server.server.get_clients()
            for client_id, c2w in zip(ids, (views[0], views[-1])):  # two keyframes' poses, one per browser
                _point(clients[client_id].camera, c2w)
            # each browser's camera reported back, settled, and decoded for
            assert _until(lambda: set(server.own_nodes) == set(ids) and server.wait_idle(5), every=follow), server.own_nodes
            cameras = _decoded_as_they_are(server, follow)
            drawn = {i: len(splats_for(mapper, cameras[i])) for i in ids}
            assert drawn[ids[0]] != drawn[ids[1]]  # two views, two decodings
            for page, client_id in zip(pages, ids):
                own = f"{drawn[client_id]} ({OWN})"
                assert _until(lambda: own in " ".join(page.inner_text("body").split()), timeout=30), page.inner_text("body")
                assert len(server.own_nodes[client_id].buffer) == drawn[client_id]
            # a keyframe selected in one browser is answered in that browser alone
            kf = mapper.training_views()[1]
            server.selections.put((ids[0], kf.kf_id))
            assert server.serve_selection(provider)
            note = f"keyframe {kf.kf_id} (frame {kf.frame_index}): image | render"
            assert _until(lambda: note in pages[0].inner_text("body"), timeout=30), pages[0].inner_text("body")
            assert note not in pages[1].inner_text("body")
            pages[0].close()  # a browser gone: its decoding is dropped, the other keeps its own
            assert _until(lambda: ids[0] not in server.own_nodes) and ids[1] in server.own_nodes
            browser.close()
    finally:
        server.close()


@pytest.mark.slow
def test_each_browser_chooses_between_the_ply_and_the_map_decoded_for_its_camera(train_run):
    sync = _browser_or_skip()
    from segs.view import CAMERA, PLY, load_mapper
    from segs.viewer.scene import OWN, splats_for

    server, provider, follow = _serve(train_run)  # a finished run: its PLY, and its checkpoint
    mapper = load_mapper(read_run(train_run))
    c2w = np.linalg.inv(mapper.training_views()[0].w2c.numpy().astype(np.float64))
    text = lambda page: " ".join(page.inner_text("body").split())  # noqa: E731
    try:
        with sync.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=str(CHROMIUM), args=BROWSER_ARGS)
            pages, ids = _open_pages(browser, server, 2)
            _point(server.server.get_clients()[ids[0]].camera, c2w)
            assert _until(lambda: server.browser_choices() == {ids[0]: PLY, ids[1]: PLY})
            ply = f"{len(server.nodes['/map/gaussians'].buffer)} (point_cloud.ply)"
            pages[0].get_by_role("combobox", name="Gaussians").click()  # the first browser alone chooses the map
            pages[0].get_by_role("option", name=CAMERA).click()
            assert _until(lambda: set(server.own_nodes) == {ids[0]} and server.wait_idle(5), every=follow), server.own_nodes
            own = f"{len(splats_for(mapper, _decoded_as_they_are(server, follow)[ids[0]]))} ({OWN})"
            assert _until(lambda: own in text(pages[0]), timeout=30), text(pages[0])
            assert ply in text(pages[1]) and OWN not in text(pages[1])  # the other one still draws the PLY
            pages[0].get_by_role("combobox", name="Gaussians").click()  # and back: the PLY again
            pages[0].get_by_role("option", name=PLY).click()
            assert _until(lambda: not server.own_nodes and server.wait_idle(5), every=follow), server.own_nodes
            assert _until(lambda: ply in text(pages[0]), timeout=30) and OWN not in text(pages[0]), text(pages[0])
            browser.close()
    finally:
        server.close()


def test_only_gaussians_that_can_change_a_pixel_are_sent():
    n = 6
    op = np.array([0.0, 1e-3, MIN_OPACITY * 0.99, MIN_OPACITY, 0.5, 1.0], np.float32)
    splats = Splats(np.arange(3 * n, dtype=np.float32).reshape(n, 3), np.tile([1, 0, 0, 0], (n, 1)).astype(np.float32),
                    np.full((n, 3), 0.1, np.float32), op, np.full((n, 3), 0.5, np.float32))  # fmt: skip
    shown = splats.visible()
    assert len(shown) == 3 and np.array_equal(shown.opacities, op[3:]) and np.array_equal(shown.means, splats.means[3:])
    assert splats.visible(0.0) is splats


def test_browsers_drawing_one_splats_share_its_covariances():
    from segs.viewer.scene import covariances

    rng = np.random.default_rng(0)
    q, sc = rng.normal(size=(50, 4)).astype(np.float32), rng.uniform(0.01, 0.1, (50, 3)).astype(np.float32)
    opacities, colors = np.linspace(0.1, 1, 50, dtype=np.float32), np.full((50, 3), 0.5, np.float32)
    g = Splats(rng.normal(size=(50, 3)).astype(np.float32), q, sc, opacities, colors)
    first = g.covariances()
    assert g.covariances() is first  # computed once for every browser drawing it (splats_for_each)
    np.testing.assert_array_equal(first, covariances(q, sc))
    half = g.visible(0.5)  # another Splats: its own
    np.testing.assert_array_equal(half.covariances(), first[g.opacities >= 0.5])


def test_a_snapshot_replacing_one_not_yet_drawn_keeps_the_decodings_it_does_not_renew():
    from segs.viewer.scene import Snapshot, merged

    def splats(n: int) -> Splats:
        return Splats(np.zeros((n, 3), np.float32), np.tile([1, 0, 0, 0], (n, 1)).astype(np.float32), np.full((n, 3), 0.1, np.float32),
                      np.ones(n, np.float32), np.full((n, 3), 0.5, np.float32))  # fmt: skip

    shared, a, b, a2 = splats(5), splats(1), splats(2), splats(3)
    pending = Snapshot(splats=shared, splats_id=1, splats_label="every one", per_browser={1: a, 2: b}, panel={"step": "10"})
    newer = Snapshot(splats_id=2, per_browser={1: a2}, panel={"step": "11"})  # browser 1 moved: decoded for it alone
    drawn = merged(pending, newer)
    assert drawn.splats is shared and drawn.splats_id == 1 and drawn.splats_label == "every one"  # the shared ones kept
    assert drawn.per_browser == {1: a2, 2: b} and drawn.panel == {"step": "11"}  # browser 2's decoding kept, 1's renewed
    fresh = Snapshot(splats=splats(4), splats_id=3, splats_label="point_cloud.ply")  # new shared Gaussians decide all
    assert merged(drawn, fresh) is fresh and not fresh.per_browser
    assert merged(None, newer) is newer
    # browser 2 shown the shared Gaussians again (segs.view: it chose the PLY), then browser 1 too
    back = merged(drawn, Snapshot(splats_id=4, dropped=frozenset({2})))
    assert back.per_browser == {1: a2} and back.dropped == {2} and back.splats is shared
    assert merged(back, Snapshot(splats_id=5, dropped=frozenset({1}))).dropped == {1, 2}
    again = merged(back, Snapshot(splats_id=5, per_browser={2: b}))  # 2 chose its own again before the drop was drawn
    assert again.per_browser == {1: a2, 2: b} and not again.dropped
    assert merged(again, Snapshot(splats_id=6, dropped=frozenset({1}))).per_browser == {2: b}
