"""What the viewer draws: one `Snapshot` of a run (numpy only), and the geometry that turns it
into scene nodes (covariances, camera centres, the ground truth in the estimated frame).

A snapshot is taken on the thread that owns the map (between training steps, between tracked
frames, once for a finished run) and drawn by the server's own thread; its arrays are copies or
arrays that their owner replaces rather than edits, so drawing never races with training.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

from segs.data.frame import Camera
from segs.modules.contract import MIN_OPACITY, GaussianCloud, GaussianMapper
from segs.trajectory import alignment


@dataclass
class Splats:
    """Gaussians to draw: means [N,3], quats [N,4] wxyz, scales [N,3], opacities [N], colors [N,3]
    (float32 numpy, colours and opacities in [0,1])."""

    means: np.ndarray
    quats: np.ndarray
    scales: np.ndarray
    opacities: np.ndarray
    colors: np.ndarray
    _covariances: np.ndarray | None = field(default=None, init=False, repr=False, compare=False)

    @classmethod
    def from_cloud(cls, cloud: GaussianCloud) -> "Splats":
        return cls(*(t.numpy().astype(np.float32, copy=False) for t in
                     (cloud.means, cloud.quats, cloud.scales, cloud.opacities, cloud.colors)))  # fmt: skip

    def __len__(self) -> int:
        return len(self.means)

    def visible(self, min_opacity: float = MIN_OPACITY) -> "Splats":
        """The Gaussians with opacity >= min_opacity (the rest cannot change an 8-bit pixel):
        what the browser is sent. A SEGS map decodes k per anchor and most of them are near 0."""
        keep = self.opacities >= min_opacity
        if keep.all():
            return self
        return Splats(*(a[keep] for a in (self.means, self.quats, self.scales, self.opacities, self.colors)))

    def covariances(self) -> np.ndarray:
        """[N,3,3] R diag(scale^2) R^T, computed once: browsers at the same camera draw one Splats."""
        if self._covariances is None:
            self._covariances = covariances(self.quats, self.scales)
        return self._covariances


@dataclass
class KeyframeNode:
    """A keyframe's camera: w2c [4,4], intrinsics, and a small image for its frustum (or None)."""

    kf_id: int
    frame_index: int
    w2c: np.ndarray
    camera: Camera
    thumbnail: np.ndarray | None = None


@dataclass
class Trajectories:
    """Estimated camera-to-world poses est_c2w [M,4,4] at est_t [M]; ground truth gt_c2w [N,4,4]
    at gt_t [N] (NaN rows where unknown) or None; align: how the ground truth is brought into
    the estimated frame (se3 / sim3 / none, the run's ATE alignment)."""

    est_t: np.ndarray
    est_c2w: np.ndarray
    gt_t: np.ndarray | None = None
    gt_c2w: np.ndarray | None = None
    align: str = "se3"

    def estimated_centres(self) -> np.ndarray:
        """[M,3]."""
        return self.est_c2w[:, :3, 3]

    def ground_truth_centres(self) -> np.ndarray | None:
        """[K,3] ground-truth camera centres in the estimated frame (the inverse of the ATE
        alignment), or None without ground truth or with fewer than 3 associated poses."""
        if self.gt_c2w is None or self.gt_t is None:
            return None
        found = alignment(self.est_t, self.est_c2w, self.gt_t, self.gt_c2w, self.align)
        if found is None:
            return None
        r, t, s = found
        ok = np.isfinite(self.gt_c2w.reshape(len(self.gt_c2w), -1)).all(axis=1)
        return (self.gt_c2w[ok, :3, 3] - t) @ r / s


DRAWN_ROW = "Gaussians drawn (opacity >= 1/255)"  # the panel's row of what a browser draws (the server writes it per browser)


@dataclass
class Snapshot:
    """One state of a run.

    splats: the Gaussians every browser is shown unless it has its own, or None (a tracking-only
    run, nothing mapped yet, or the shared ones unchanged); splats_id changes when they do (the
    server sends them again only then); splats_label: what they were decoded for (the panel's
    words).
    per_browser: client id -> the Gaussians decoded for that browser's camera, drawn for
    it alone; a browser not in it keeps its own unless the snapshot brings new shared splats.
    dropped: browsers whose own Gaussians are removed (they are shown the shared ones again).
    points [M,3] / point_colors [M,3] in [0,1]: the SLAM map points. panel: label -> value, in
    order (markdown table of the page; the server adds DRAWN_ROW after "Gaussians").
    """

    splats: Splats | None = None
    splats_id: int = 0
    splats_label: str = ""
    per_browser: dict[int, Splats | None] = field(default_factory=dict)
    dropped: frozenset[int] = frozenset()
    points: np.ndarray | None = None
    point_colors: np.ndarray | None = None
    trajectories: Trajectories | None = None
    keyframes: list[KeyframeNode] = field(default_factory=list)
    panel: dict[str, str] = field(default_factory=dict)


def merged(pending: Snapshot | None, newer: Snapshot) -> Snapshot:
    """The snapshot to draw when `newer` arrives before `pending` was drawn. Newer shared splats
    decide everything (a browser newer does not decode for is shown them); without them, newer
    keeps pending's shared splats, its decodings for the browsers newer neither decodes for nor
    drops, and its drops of the browsers newer does not decode for."""
    if pending is None or newer.splats is not None:
        return newer
    kept = {cid: g for cid, g in pending.per_browser.items() if cid not in newer.dropped}
    dropped = (pending.dropped - newer.per_browser.keys()) | newer.dropped
    return replace(newer, splats=pending.splats, splats_id=pending.splats_id, splats_label=pending.splats_label,
                   per_browser={**kept, **newer.per_browser}, dropped=dropped)  # fmt: skip


def rotations(quats: np.ndarray) -> np.ndarray:
    """quats [N,4] wxyz (any norm) -> rotation matrices [N,3,3]."""
    q = quats / np.linalg.norm(quats, axis=1, keepdims=True).clip(1e-12)
    w, x, y, z = q.T
    return np.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], 1).reshape(-1, 3, 3)  # fmt: skip


def covariances(quats: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """quats [N,4] wxyz (any norm), scales [N,3] -> covariances [N,3,3] float32."""
    m = rotations(quats) * scales[:, None, :]
    return (m @ m.transpose(0, 2, 1)).astype(np.float32)


SETTLE_S = 0.3  # a browser's camera is decoded for once still this long after a move (not at every frame of a drag)


@dataclass
class BrowserCamera:
    """A browser's camera: w2c [4,4] float64 (OpenCV axes: x right, y down, z forward), the
    pinhole intrinsics of its canvas, and when it last moved (time.time() of the server)."""

    w2c: np.ndarray
    camera: Camera
    moved_at: float

    def settled_after(self, t: float) -> bool:
        """Whether it moved after time t (time.time()) and has been still since for SETTLE_S."""
        return self.moved_at > t and time.time() - self.moved_at >= SETTLE_S


def splats_for(mapper: GaussianMapper, camera: BrowserCamera | None) -> Splats | None:
    """The mapper's Gaussians a viewer draws (opacity >= MIN_OPACITY): those a render from the
    browser's camera draws, decoded for it, or without one every Gaussian as exported; None
    before the map has any."""
    cloud = mapper.gaussians() if camera is None else mapper.gaussians(camera.w2c, camera.camera)
    return Splats.from_cloud(cloud).visible() if cloud is not None and len(cloud) else None


class DecodedCameras:
    """When each browser's camera had last moved at its latest decoding (client id -> time), to
    tell which cameras moved since."""

    def __init__(self):
        self.moved_at: dict[int, float] = {}

    def moved(self, cameras: dict[int, BrowserCamera]) -> dict[int, BrowserCamera]:
        """The cameras (client id -> camera) that moved since their latest decoding (or were never
        decoded for) and have been still since for SETTLE_S."""
        return {cid: cam for cid, cam in cameras.items() if cam.settled_after(self.moved_at.get(cid, 0.0))}

    def mark(self, cameras: dict[int, BrowserCamera]) -> None:
        """Record that `cameras` were decoded for now."""
        self.moved_at.update({cid: cam.moved_at for cid, cam in cameras.items()})


def splats_for_each(mapper: GaussianMapper, cameras: dict[int, BrowserCamera]) -> dict[int, Splats | None]:
    """splats_for each browser's camera (client id -> camera), decoded once for browsers whose
    cameras are the same (pose and canvas: tabs that have not moved since they opened)."""
    decoded: dict[tuple, Splats | None] = {}
    out = {}
    for client_id, cam in cameras.items():
        key = (cam.w2c.tobytes(), cam.camera)
        if key not in decoded:
            decoded[key] = splats_for(mapper, cam)
        out[client_id] = decoded[key]
    return out


EVERY_ONE = "every one, decoded for the first keyframe"  # what the shared Gaussians of a map are
OWN = "decoded for this camera's view"  # what a browser's own Gaussians are


def browser_camera(wxyz: np.ndarray, position: np.ndarray, fov: float, width: int, height: int, moved_at: float) -> BrowserCamera:
    """A browser's camera from viser's state: orientation wxyz [4] and position [3] of the camera
    in the world (c2w, OpenCV axes), vertical field of view fov (radians), canvas width x height."""
    c2w = np.eye(4)
    c2w[:3, :3], c2w[:3, 3] = rotations(np.asarray(wxyz, np.float64)[None])[0], position
    w, h = max(int(width), 1), max(int(height), 1)
    f = h / (2.0 * np.tan(fov / 2.0))
    return BrowserCamera(np.linalg.inv(c2w), Camera(f, f, w / 2.0, h / 2.0, w, h), float(moved_at))


@dataclass
class Framing:
    """Where the browsers' camera starts: position [3] looking at look_at [3] with up [3]; the
    map's centre [3] and extent (the scale of the frustums, lines and points)."""

    centre: np.ndarray
    extent: float
    up: np.ndarray
    position: np.ndarray
    look_at: np.ndarray


def framing(snapshot: Snapshot, back: float = 0.6, rise: float = 0.3) -> Framing | None:
    """The snapshot's framing, or None when it shows nothing.

    centre = median of the map (points or Gaussians, else camera centres), extent = the 90th
    percentile of their distance to it, up = the cameras' mean up direction (-y of OpenCV). The
    camera starts behind the first keyframe (back * extent behind it, rise * extent above),
    looking where it looked: the run's first view with its frustum in sight; without cameras,
    from above and aside the centre."""
    cams = [np.linalg.inv(k.w2c) for k in sorted(snapshot.keyframes, key=lambda k: k.kf_id)]
    if not cams and snapshot.trajectories is not None and len(snapshot.trajectories.est_c2w):
        cams = list(snapshot.trajectories.est_c2w)
    parts = [p for p in (snapshot.points, snapshot.splats.means if snapshot.splats is not None else None) if p is not None and len(p)]
    where = np.concatenate(parts) if parts else (np.stack([c[:3, 3] for c in cams]) if cams else None)
    if where is None or not len(where):
        return None
    centre = np.median(where, axis=0)
    extent = float(np.percentile(np.linalg.norm(where - centre, axis=1), 90)) or 1.0
    up = -np.mean([c[:3, 1] for c in cams], axis=0) if cams else np.array([0.0, 0.0, 1.0])
    up = up / np.linalg.norm(up) if np.linalg.norm(up) > 1e-6 else np.array([0.0, 0.0, 1.0])
    if cams:
        forward, origin = cams[0][:3, 2], cams[0][:3, 3]
        return Framing(centre, extent, up, origin - back * extent * forward + rise * extent * up, origin + extent * forward)
    side = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    return Framing(centre, extent, up, centre + extent * (1.6 * up + 1.6 * side / np.linalg.norm(side)), centre)


def thumbnail(image: np.ndarray, width: int = 96) -> np.ndarray:
    """image [H,W,3] uint8 -> [h,width,3] uint8 (nearest pixels: cheap on the training thread)."""
    h, w = image.shape[:2]
    rows = (np.arange(max(int(round(h * width / w)), 1)) * h / max(int(round(h * width / w)), 1)).astype(int)
    cols = (np.arange(width) * w / width).astype(int)
    return np.ascontiguousarray(image[rows][:, cols])
