"""The viser server of a run: a drawing thread turns the latest `Snapshot` into scene nodes, each
browser's panel shows the run's numbers, and a keyframe selected in a browser (its frustum
clicked, or the browser's keyframe list) is answered in that browser with its image beside the
render from its pose.

The Gaussians: a snapshot's shared decoding is a scene node every browser sees; a browser with a
decoding of its own (for its camera, `Snapshot.per_browser`) gets a node of the same name for it
alone, which hides the shared one from that browser (viser's client-scoped nodes), and its panel
says what it draws.

The thread that owns the map hands snapshots over with `submit` (the newest replaces one not yet
drawn, keeping the decodings of it that the newest does not renew) and answers selections with
`serve_selection(provider)` when it has time: no call made by the browser ever touches the map.
"""
from __future__ import annotations

import contextlib
import errno
import io
import logging
import math
import queue
import socket
import threading
import time
from typing import Callable

import numpy as np

from segs.errors import ConfigError
from segs.viewer.scene import DRAWN_ROW, OWN, BrowserCamera, Framing, KeyframeNode, Snapshot, Splats, browser_camera, framing, merged

log = logging.getLogger(__name__)

PORT_TRIES = 100
EST_COLOR, GT_COLOR, KF_COLOR = (230, 80, 20), (40, 160, 60), (30, 90, 200)
# provider of a selection: kf_id -> (image [H,W,3] uint8, render [H,W,3] uint8 or None, note)
Provider = Callable[[int], "tuple[np.ndarray, np.ndarray | None, str]"]


def port_is_free(host: str, port: int) -> bool:
    """Whether a server could bind (host, port) now (as asyncio binds: SO_REUSEADDR)."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError as err:
            if err.errno in (errno.EADDRINUSE, errno.EACCES):
                return False
            raise ConfigError(f"viewer.host={host}: cannot serve on it ({err.strerror})") from None
    return True


def choose_port(host: str, port: int | None, first_port: int) -> tuple[int, str | None]:
    """(port to serve on, one line saying a busy port was skipped, or None).

    port given: that one or ConfigError (exit 2) when it is busy; None: the first free port from
    first_port on."""
    if port is not None:
        if not port_is_free(host, port):
            raise ConfigError(f"viewer port {port} on {host} is busy (given by viewer.port / --port); choose another, "
                              "or give none to take the first free port")  # fmt: skip
        return port, None
    for p in range(first_port, min(first_port + PORT_TRIES, 65536)):
        if port_is_free(host, p):
            return p, None if p == first_port else f"viewer: port {first_port} on {host} is busy; serving on port {p}"
    raise ConfigError(f"viewer.first_port={first_port}: ports {first_port}-{first_port + PORT_TRIES - 1} on {host} are all busy")


class ViewerServer:
    """A viser server showing snapshots of one run (see the module docstring)."""

    def __init__(self, host: str, port: int | None, first_port: int, title: str):
        chosen, self.note = choose_port(host, port, first_port)
        import viser  # the `viewer` extra, imported only when a server starts

        logging.getLogger("websockets").setLevel(logging.WARNING)  # one line per connection otherwise
        quiet = logging.getLogger("websockets.server")
        if not any(isinstance(f, _HandshakeNoise) for f in quiet.filters):
            quiet.addFilter(_HandshakeNoise())
        self._viser = viser
        self.selections: queue.Queue[tuple[int, int]] = queue.Queue()  # (client id, kf_id) in the order selected
        self.drawn = 0  # snapshots drawn so far (tests wait on it)
        self.draw_ms: list[float] = []  # CPU time of the drawing thread per snapshot
        self._pending: Snapshot | None = None
        self._cond = threading.Condition()
        self._closed = False
        self._drawing = False
        self._frustums: dict[int, object] = {}
        self.nodes: dict[str, object] = {}  # scene node name -> viser handle, of what is drawn now
        self._splats_id = None
        # per browser (client id), guarded by _lock (the drawing thread, viser's connect / disconnect handlers):
        self._lock = threading.Lock()
        self.own_nodes: dict[int, object] = {}  # the Gaussians decoded for its camera (the node shadowing the shared one)
        self._own_rows: dict[int, str] = {}  # what its own node draws, for its panel
        self._guis: dict[int, _BrowserGui] = {}  # its panel, keyframe list and selected keyframe
        self._rows: dict[str, str] = {}  # the latest snapshot's panel
        self._shared_row: str | None = None  # what the shared node draws (None: no Gaussians drawn yet)
        self.framed: Framing | None = None  # where the browsers' camera was put (the first snapshot's framing)
        self._keyframe_labels: dict[str, int] = {}  # the keyframe lists' options -> kf_id
        self._choice: tuple | None = None  # add_choice's dropdown, made in every browser's part
        self._title = title
        with contextlib.redirect_stdout(io.StringIO()):  # viser's banner: the address is printed in one line instead
            self.server = viser.ViserServer(host=host, port=chosen, label=title, verbose=False)
        self.port = self.server.get_port()
        if self.port != chosen:  # taken between the check and the bind
            if port is not None:
                self.close()
                raise ConfigError(f"viewer port {port} on {host} is busy (given by viewer.port / --port)")
            self.note = f"viewer: port {chosen} on {host} is busy; serving on port {self.port}"
        self.url = f"http://{socket.gethostname() if host in ('0.0.0.0', '::') else host}:{self.port}"
        # no share button: it would publish the run through viser's public relay
        self.server.gui.configure_theme(show_share_button=False, control_width="large")
        self.server.on_client_connect(self._connected)
        self.server.on_client_disconnect(self._disconnected)
        self._thread = threading.Thread(target=self._draw_loop, name="segs-viewer-draw", daemon=True)
        self._thread.start()

    # -- the owner's side -----------------------------------------------------------------------
    def clients(self) -> int:
        """Browsers connected now."""
        return len(self.server.get_clients())

    def browser_cameras(self) -> dict[int, BrowserCamera]:
        """The cameras of the connected browsers that have reported one: client id -> camera."""
        cameras = {}
        for client_id, client in self.server.get_clients().items():
            cam = client.camera
            try:  # viser refuses to read a camera that the browser has not reported yet
                state = (cam.wxyz, cam.position, cam.fov, cam.image_width, cam.image_height, cam.update_timestamp)
            except AssertionError:
                continue
            if state[-1] > 0:
                cameras[client_id] = browser_camera(*state)
        return cameras

    def submit(self, snapshot: Snapshot) -> None:
        """Hand a snapshot to the drawing thread (replacing one it has not drawn yet, whose
        decodings that this one does not renew it keeps: scene.merged)."""
        with self._cond:
            self._pending = merged(self._pending, snapshot)
            self._cond.notify()

    def wait_idle(self, timeout: float) -> bool:
        """Wait until every snapshot submitted so far is drawn; False on timeout."""
        with self._cond:
            return self._cond.wait_for(lambda: self._pending is None and not self._drawing, timeout)

    def serve_selection(self, provider: Provider) -> bool:
        """Answer the newest keyframe selected in each browser, if any, with provider(kf_id) shown
        in that browser's panel (image | render); returns whether one was answered."""
        newest: dict[int, int] = {}
        while True:
            try:
                client_id, kf_id = self.selections.get_nowait()
            except queue.Empty:
                break
            newest[client_id] = kf_id
        answered = False
        for client_id, kf_id in newest.items():
            with self._lock:
                gui = self._guis.get(client_id)
            if gui is None:  # gone
                continue
            image, render, note = provider(kf_id)
            gui.show_pair(image if render is None else np.concatenate([image, render], axis=1), note)
            answered = True
        return answered

    def add_choice(self, label: str, options: tuple[str, ...], initial: str, hint: str) -> None:
        """A dropdown in each browser's part of the page (above its keyframe list), its own choice
        (browser_choices), for the browsers connected now and those that connect later."""
        with self._lock:
            self._choice = (label, options, initial, hint)
            for gui in self._guis.values():
                gui.add_choice(*self._choice)

    def browser_choices(self) -> dict[int, str]:
        """Each connected browser's value of the add_choice dropdown: client id -> option."""
        with self._lock:
            return {client_id: gui.choice.value for client_id, gui in self._guis.items() if gui.choice is not None}

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify()
        with contextlib.redirect_stdout(io.StringIO()):  # viser's "Server stopped"
            self.server.stop()

    # -- the browser's side ---------------------------------------------------------------------
    def _connected(self, client) -> None:
        """A browser's panel and keyframe list (viser's handler of a new connection; a reload is a
        new client)."""
        with self._lock:
            content = self._markdown_for(client.client_id) if self._rows else f"**{self._title}**\n\nwaiting for the first snapshot"
            gui = _BrowserGui(client.gui, content, ("none", *self._keyframe_labels))
            gui.keyframes.on_update(lambda _: self._select(client.client_id, self._keyframe_labels.get(gui.keyframes.value)))
            if self._choice is not None:
                gui.add_choice(*self._choice)
            self._guis[client.client_id] = gui

    def _disconnected(self, client) -> None:
        with self._lock:
            for per_browser in (self.own_nodes, self._own_rows, self._guis):
                per_browser.pop(client.client_id, None)

    def _markdown_for(self, client_id: int) -> str:
        """The panel of one browser: the snapshot's rows with what this browser draws after
        "Gaussians", once there are Gaussians to draw (call with _lock held)."""
        drawn = self._own_rows.get(client_id, self._shared_row)
        rows = {}
        for key, value in self._rows.items():
            rows[key] = value
            if key == "Gaussians" and drawn is not None:
                rows[DRAWN_ROW] = drawn
        return _markdown(rows)

    def _select(self, client_id: int | None, kf_id: int | None) -> None:
        if client_id is not None and kf_id is not None:
            self.selections.put((int(client_id), int(kf_id)))

    # -- drawing --------------------------------------------------------------------------------
    def _draw_loop(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._pending is not None or self._closed)
                if self._closed:
                    return
                snapshot, self._pending, self._drawing = self._pending, None, True
            t0 = time.thread_time()
            try:
                self._draw(snapshot)
            except Exception:  # noqa: BLE001 - a drawing failure must not end the run it shows
                log.exception("viewer: drawing a snapshot failed")
            self.draw_ms.append((time.thread_time() - t0) * 1000.0)
            with self._cond:
                self.drawn, self._drawing = self.drawn + 1, False
                self._cond.notify_all()

    def _draw(self, s: Snapshot) -> None:
        scene = self.server.scene
        frame = framing(s)
        if frame is not None and self.framed is None:
            self._frame_camera(frame)
        extent = frame.extent if frame is not None else 1.0
        if s.splats is not None and s.splats_id != self._splats_id:
            self.nodes["/map/gaussians"] = _add_splats(scene, s.splats)
            self._splats_id, self._shared_row = s.splats_id, f"{len(s.splats)} ({s.splats_label})"
        if s.points is not None and len(s.points):
            colors = (np.clip(s.point_colors, 0, 1) * 255).astype(np.uint8)
            self.nodes["/map/points"] = scene.add_point_cloud("/map/points", s.points.astype(np.float32), colors,
                                                              point_size=0.004 * extent, point_shape="circle")  # fmt: skip
        if s.trajectories is not None:
            self._draw_trajectories(s, extent)
        self._draw_keyframes(s.keyframes, extent)
        self._draw_per_browser(s)

    def _draw_per_browser(self, s: Snapshot) -> None:
        """Each browser's own decoding (s.per_browser) over the shared one, and every panel. A new
        shared decoding takes the place of the own decodings the snapshot does not renew."""
        clients = self.server.get_clients()
        with self._lock:
            gone = set(self.own_nodes) - set(s.per_browser) if s.splats is not None else s.dropped & set(self.own_nodes)
            for client_id in gone:
                self.own_nodes.pop(client_id).remove()
                self._own_rows.pop(client_id, None)
            for client_id, splats in s.per_browser.items():
                client = clients.get(client_id)
                if client is None or splats is None:  # gone, or nothing in its view: it keeps what it has
                    continue
                self.own_nodes[client_id] = _add_splats(client.scene, splats)
                self._own_rows[client_id] = f"{len(splats)} ({OWN})"
            self._rows = dict(s.panel)
            for client_id, gui in self._guis.items():
                gui.panel.content = self._markdown_for(client_id)

    def _draw_trajectories(self, s: Snapshot, extent: float) -> None:
        for name, centres, color in (("/trajectory/estimated", s.trajectories.estimated_centres(), EST_COLOR),
                                     ("/trajectory/ground_truth", s.trajectories.ground_truth_centres(), GT_COLOR)):  # fmt: skip
            if centres is not None and len(centres) >= 2:
                segments = np.stack([centres[:-1], centres[1:]], 1).astype(np.float32)
                self.nodes[name] = self.server.scene.add_line_segments(name, segments, color, thickness=0.003 * extent)

    def _draw_keyframes(self, keyframes: list[KeyframeNode], extent: float) -> None:
        tf = self._viser.transforms
        seen = set()
        for kf in keyframes:
            c2w = np.linalg.inv(kf.w2c)
            wxyz, pos = tf.SO3.from_matrix(c2w[:3, :3]).wxyz, c2w[:3, 3]
            seen.add(kf.kf_id)
            handle = self._frustums.get(kf.kf_id)
            if handle is not None:
                handle.wxyz, handle.position = wxyz, pos
                continue
            cam = kf.camera
            handle = self.server.scene.add_camera_frustum(
                f"/keyframes/kf_{kf.kf_id:05d}", fov=2 * math.atan(cam.height / (2 * cam.fy)), aspect=cam.width / cam.height,
                scale=0.06 * extent, thickness=0.002 * extent, color=KF_COLOR, image=kf.thumbnail, format="jpeg",
                wxyz=wxyz, position=pos)  # fmt: skip
            handle.on_click(lambda event, k=kf.kf_id: self._select(event.client_id, k))
            self._frustums[kf.kf_id] = self.nodes[handle.name] = handle
        for kf_id in set(self._frustums) - seen:  # keyframes culled by the frontend
            handle = self._frustums.pop(kf_id)
            self.nodes.pop(handle.name, None)
            handle.remove()
        labels = {f"kf {kf.kf_id} (frame {kf.frame_index})": kf.kf_id for kf in sorted(keyframes, key=lambda k: k.kf_id)}
        if labels.keys() != self._keyframe_labels.keys():
            with self._lock:
                self._keyframe_labels = labels
                for gui in self._guis.values():
                    gui.keyframes.options = ("none", *labels)

    def _frame_camera(self, frame: Framing) -> None:
        """Point the browsers' camera at the map (scene.framing), once."""
        self.framed = frame
        up = tuple(float(v) for v in frame.up)
        self.server.scene.set_up_direction(up)
        cam = self.server.initial_camera
        cam.position, cam.look_at, cam.up = tuple(frame.position), tuple(frame.look_at), up
        for client in self.server.get_clients().values():
            client.camera.position, client.camera.look_at, client.camera.up_direction = tuple(frame.position), tuple(frame.look_at), up


class _BrowserGui:
    """One browser's part of the page, above the shared controls: the panel (markdown table), a
    choice (ViewerServer.add_choice), the keyframe list and the selected keyframe's note and
    image | render."""

    ORDER = -4.0  # viser orders GUI elements by this number; the shared ones count up from 1

    def __init__(self, gui, content: str, options: tuple[str, ...]):
        self._gui, self.choice = gui, None
        self.panel = gui.add_markdown(content, order=self.ORDER)
        self.keyframes = gui.add_dropdown("keyframe", options, initial_value="none", order=self.ORDER + 1,
                                          hint="show a keyframe's image beside the render from its pose")  # fmt: skip
        self.pair_note = gui.add_markdown("", visible=False, order=self.ORDER + 2)
        self.pair = gui.add_image(np.zeros((1, 2, 3), np.uint8), label="image | render", format="jpeg", visible=False,
                                  order=self.ORDER + 3)  # fmt: skip

    def add_choice(self, label: str, options: tuple[str, ...], initial: str, hint: str) -> None:
        self.choice = self._gui.add_dropdown(label, options, initial_value=initial, hint=hint, order=self.ORDER + 0.5)

    def show_pair(self, pair: np.ndarray, note: str) -> None:
        """pair [H,W,3] uint8 (image, or image | render) shown with its note."""
        self.pair.image = _fit_width(pair, 960)
        self.pair_note.content = note
        self.pair.visible = self.pair_note.visible = True


class _HandshakeNoise(logging.Filter):
    """Drops websockets' traceback for a connection closed before its request (a browser's
    speculative preconnect, a port probe): nothing went wrong on the server."""

    def filter(self, record: logging.LogRecord) -> bool:
        return record.getMessage() != "opening handshake failed"


def _add_splats(scene, g: Splats):
    """The Gaussians as the node "/map/gaussians" of a scene (the server's, or one browser's)."""
    return scene.add_gaussian_splats("/map/gaussians", centers=g.means, covariances=g.covariances(), rgbs=g.colors.clip(0, 1),
                                     opacities=g.opacities.clip(0, 1)[:, None])  # fmt: skip


def _markdown(panel: dict[str, str]) -> str:
    rows = "\n".join(f"| {k} | {v} |" for k, v in panel.items())
    return f"| | |\n|---|---|\n{rows}"


def _fit_width(image: np.ndarray, width: int) -> np.ndarray:
    """image [H,W,3] uint8 shrunk (nearest pixels) to at most `width` columns."""
    h, w = image.shape[:2]
    if w <= width:
        return image
    rows = (np.arange(int(h * width / w)) * w / width).astype(int)
    cols = (np.arange(width) * w / width).astype(int)
    return np.ascontiguousarray(image[rows][:, cols])
