"""The known-poses frontend: ground-truth trajectory, structure from ORB keypoints.

For mapping-only studies (`slam=known_poses`). Keyframes are chosen by frame gap and motion;
each keyframe contributes ORB keypoints lifted to 3D from depth (RGB-D), from stereo disparity
(stereo) or by triangulation against the previous keyframe with the known poses (monocular).
Keypoints matched to a keypoint of the previous keyframe that already produced a point are not
lifted again, so a surface seen by many keyframes does not pile up duplicate points.
"""
from __future__ import annotations

import cv2
import numpy as np

from segs.data.frame import Camera, Frame
from segs.errors import ConfigError
from segs.slam.base import STATE_FORMAT, FrameResult, Frontend, MapUpdate


def _gray(rgb: np.ndarray) -> np.ndarray:
    return cv2.cvtColor((np.clip(rgb, 0, 1) * 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)


class KnownPosesFrontend(Frontend):
    """Ground-truth poses + ORB structure.

    keyframe_every: max frame gap between keyframes; kf_translation (m) / kf_rotation_deg: motion
    since the last keyframe that also triggers one; n_features / fast_threshold: ORB settings;
    depth_range: valid depth (m) for lifting; max_reproj_px / min_parallax_deg: monocular
    triangulation checks; stereo_num_disparities: SGBM search range (multiple of 16);
    max_hamming: largest descriptor distance of a match with the previous keyframe;
    point_source: "orb" (keypoints, like an indirect SLAM's map) or "grid" (every grid_stride-th
    pixel with depth, RGB-D / stereo only: dense structure for texture-poor scenes). Every value
    is conf/slam/known_poses.yaml's (segs.config.slam_frontend(camera, sensor, "known_poses")).
    """

    uses_ground_truth_poses = True

    def __init__(self, camera: Camera, sensor: str, *, keyframe_every: int, kf_translation: float, kf_rotation_deg: float,
                 n_features: int, fast_threshold: int, depth_range: tuple[float, float], max_reproj_px: float,
                 min_parallax_deg: float, stereo_num_disparities: int, max_hamming: int, point_source: str,
                 grid_stride: int):  # fmt: skip
        if keyframe_every < 1:
            raise ConfigError(f"slam.keyframe_every={keyframe_every} is out of range: expected >= 1")
        if n_features < 1:
            raise ConfigError(f"slam.n_features={n_features} is out of range: expected >= 1")
        if sensor not in ("mono", "stereo", "rgbd"):
            raise ConfigError(f"sensor.mode={sensor!r}: expected mono, stereo or rgbd")
        if point_source not in ("orb", "grid") or (point_source == "grid" and sensor == "mono"):
            raise ConfigError(f"slam.point_source={point_source!r}: expected orb, or grid with an rgbd / stereo camera")
        if grid_stride < 1:
            raise ConfigError(f"slam.grid_stride={grid_stride} is out of range: expected >= 1")
        self.point_source, self.grid_stride = point_source, grid_stride
        self.camera, self.sensor = camera, sensor
        self.keyframe_every, self.kf_translation = keyframe_every, kf_translation
        self.kf_rotation = np.deg2rad(kf_rotation_deg)
        self.depth_range, self.max_reproj_px = tuple(depth_range), max_reproj_px
        self.min_parallax = np.deg2rad(min_parallax_deg)
        self.orb = cv2.ORB_create(nfeatures=n_features, fastThreshold=fast_threshold)
        self.matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
        self.max_hamming = max_hamming
        self.stereo_num_disparities = stereo_num_disparities
        self._poses: dict[int, np.ndarray] = {}
        self._lost: list[int] = []
        self._kf_frames: dict[int, int] = {}
        self._last_kf: dict | None = None  # {"w2c", "kps" [K,2], "desc", "has_point" [K], "frame"}
        self._pending = MapUpdate()

    # -- Frontend interface ---------------------------------------------------------------------
    def process(self, frame: Frame) -> FrameResult:
        if frame.pose_c2w is None or not np.isfinite(frame.pose_c2w).all():
            self._lost.append(frame.index)
            return FrameResult(frame.index, None)
        w2c = np.linalg.inv(frame.pose_c2w)
        self._poses[frame.index] = w2c
        if not self._is_keyframe(frame.index, w2c):
            return FrameResult(frame.index, w2c)
        kf_id = len(self._kf_frames)
        self._kf_frames[kf_id] = frame.index
        points, colors = self._lift(frame, w2c)
        self._pending = self._pending.merge(
            MapUpdate(
                new_keyframes=[kf_id],
                poses={kf_id: w2c},
                points=points,
                colors=colors,
                point_kf=np.full(len(points), kf_id, np.int64),
            )
        )
        return FrameResult(frame.index, w2c, kf_id)

    def poll(self) -> MapUpdate:
        out, self._pending = self._pending, MapUpdate()
        return out

    def finish(self) -> MapUpdate:
        return self.poll()

    def trajectory(self) -> dict[int, np.ndarray]:
        return dict(self._poses)

    def lost_frames(self) -> list[int]:
        return list(self._lost)

    def keyframe_frames(self) -> dict[int, int]:
        return dict(self._kf_frames)

    def state_dict(self) -> dict:
        """Poses, lost frames, keyframes, the last keyframe's features and the update not polled
        yet, as arrays (format segs.state.v3; states before it had no format and no pending)."""
        last = None if self._last_kf is None else {k: np.array(v) if k != "frame" else int(v) for k, v in self._last_kf.items()}
        return {"format": STATE_FORMAT, "kind": "known_poses", "frame": np.array(list(self._poses), np.int64),
                "w2c": np.array(list(self._poses.values()), np.float64).reshape(-1, 4, 4),
                "lost": np.array(self._lost, np.int64), "kf_id": np.array(list(self._kf_frames), np.int64),
                "kf_frame": np.array(list(self._kf_frames.values()), np.int64), "last_kf": last,
                "pending": self._pending.state_dict()}  # fmt: skip

    def load_state_dict(self, state: dict) -> None:
        if "format" not in state and "poses" in state:  # before segs.state.v3: dicts of arrays
            state = {"frame": np.array(list(state["poses"]), np.int64), "w2c": np.array(list(state["poses"].values())).reshape(-1, 4, 4),
                     "lost": np.array(state["lost"], np.int64), "kf_id": np.array(list(state["kf_frames"]), np.int64),
                     "kf_frame": np.array(list(state["kf_frames"].values()), np.int64), "last_kf": state["last_kf"],
                     "pending": MapUpdate().state_dict(), "format": STATE_FORMAT, "kind": "known_poses"}  # fmt: skip
        if state.get("format") != STATE_FORMAT or state.get("kind") != "known_poses":
            raise ConfigError(f"slam: the checkpoint's frontend state is {state.get('kind') or state.get('format')!r}, not a "
                              "known-poses state; resume with the frontend that wrote it")  # fmt: skip
        self._poses = {k: w.copy() for k, w in zip(state["frame"].tolist(), state["w2c"])}
        self._lost = state["lost"].tolist()
        self._kf_frames = dict(zip(state["kf_id"].tolist(), state["kf_frame"].tolist()))
        last = state["last_kf"]
        self._last_kf = None if last is None else {k: (np.array(v) if k != "frame" else int(v)) for k, v in last.items()}
        self._pending = MapUpdate.from_state(state["pending"])

    # -- keyframe decision ----------------------------------------------------------------------
    def _is_keyframe(self, index: int, w2c: np.ndarray) -> bool:
        if self._last_kf is None:
            return True
        if index - self._last_kf["frame"] >= self.keyframe_every:
            return True
        rel = w2c @ np.linalg.inv(self._last_kf["w2c"])
        angle = np.arccos(np.clip((np.trace(rel[:3, :3]) - 1) / 2, -1, 1))
        return bool(np.linalg.norm(rel[:3, 3]) > self.kf_translation or angle > self.kf_rotation)

    # -- structure ------------------------------------------------------------------------------
    def _lift(self, frame: Frame, w2c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Keypoints (or grid pixels) of this keyframe -> new world points [M,3] and colours [M,3]."""
        if self.point_source == "grid":
            return self._lift_grid(frame, w2c)
        kps, desc = self.orb.detectAndCompute(_gray(frame.rgb), None)
        uv = np.array([k.pt for k in kps], np.float32).reshape(-1, 2)
        desc = desc if desc is not None else np.zeros((0, 32), np.uint8)
        qi, ti = self._match_last(desc)
        seen = np.zeros(len(uv), bool)
        if len(qi):
            seen[qi] = self._last_kf["has_point"][ti]
        if self.sensor == "mono":
            xyz, ok = self._triangulate(uv, w2c, qi, ti)
        else:
            depth = frame.depth if self.sensor == "rgbd" else self._stereo_depth(frame)
            xyz, ok = self._backproject(uv, depth, w2c)
        ok &= ~seen
        self._last_kf = {"w2c": w2c, "uv": uv, "desc": desc, "has_point": ok | seen, "frame": frame.index}
        return xyz[ok], self._colors(frame.rgb, uv[ok])

    def _lift_grid(self, frame: Frame, w2c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        s = self.grid_stride
        v, u = np.mgrid[s // 2 : frame.rgb.shape[0] : s, s // 2 : frame.rgb.shape[1] : s]
        uv = np.stack([u.ravel(), v.ravel()], 1).astype(np.float32)
        depth = frame.depth if self.sensor == "rgbd" else self._stereo_depth(frame)
        xyz, ok = self._backproject(uv, depth, w2c)
        self._last_kf = {"w2c": w2c, "uv": uv[:0], "desc": np.zeros((0, 32), np.uint8), "has_point": ok[:0], "frame": frame.index}
        return xyz[ok], self._colors(frame.rgb, uv[ok])

    def _match_last(self, desc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Cross-checked Hamming matches with the previous keyframe: (query idx [M], train idx [M])."""
        last = self._last_kf
        if last is None or len(desc) == 0 or len(last["desc"]) == 0:
            return np.zeros(0, int), np.zeros(0, int)
        matches = [m for m in self.matcher.match(desc, last["desc"]) if m.distance < self.max_hamming]
        return np.array([m.queryIdx for m in matches], int), np.array([m.trainIdx for m in matches], int)

    def _backproject(self, uv: np.ndarray, depth: np.ndarray, w2c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        c = self.camera
        px = np.clip(np.round(uv).astype(int), 0, [depth.shape[1] - 1, depth.shape[0] - 1])
        z = depth[px[:, 1], px[:, 0]].astype(np.float64)
        ok = (z > self.depth_range[0]) & (z < self.depth_range[1]) & np.isfinite(z)
        cam = np.stack([(uv[:, 0] - c.cx) / c.fx * z, (uv[:, 1] - c.cy) / c.fy * z, z], 1)
        c2w = np.linalg.inv(w2c)
        return cam @ c2w[:3, :3].T + c2w[:3, 3], ok

    def _stereo_depth(self, frame: Frame) -> np.ndarray:
        """[H,W] metres from SGBM disparity of the rectified pair (0 where invalid)."""
        if frame.right is None or not self.camera.baseline:
            return np.zeros(frame.rgb.shape[:2], np.float32)
        sgbm = cv2.StereoSGBM_create(0, self.stereo_num_disparities, 5, P1=8 * 25, P2=32 * 25, uniquenessRatio=10)
        disp = sgbm.compute(_gray(frame.rgb), _gray(frame.right)).astype(np.float32) / 16.0
        return np.where(disp > 0.5, self.camera.fx * self.camera.baseline / np.maximum(disp, 0.5), 0.0).astype(np.float32)

    def _triangulate(self, uv: np.ndarray, w2c: np.ndarray, qi: np.ndarray, ti: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Triangulate matched keypoints against the previous keyframe with the known poses."""
        xyz, ok = np.zeros((len(uv), 3)), np.zeros(len(uv), bool)
        if len(qi) == 0:
            return xyz, ok
        last, K = self._last_kf, self.camera.K
        pts = cv2.triangulatePoints(K @ w2c[:3], K @ last["w2c"][:3], uv[qi].T.astype(np.float64), last["uv"][ti].T.astype(np.float64))
        X = (pts[:3] / np.where(np.abs(pts[3]) > 1e-12, pts[3], 1e-12)).T
        xyz[qi], ok[qi] = X, self._check_triangulated(X, uv[qi], last["uv"][ti], w2c, last["w2c"])
        return xyz, ok

    def _check_triangulated(self, X, uv_a, uv_b, w2c_a, w2c_b) -> np.ndarray:
        """Positive depth, small reprojection error in both views, enough parallax."""
        good = np.isfinite(X).all(1)
        rays = []
        for uv, w2c in ((uv_a, w2c_a), (uv_b, w2c_b)):
            cam = X @ w2c[:3, :3].T + w2c[:3, 3]
            z = cam[:, 2]
            proj = cam[:, :2] / np.where(z > 1e-9, z, 1e-9)[:, None] * [self.camera.fx, self.camera.fy] + [self.camera.cx, self.camera.cy]
            good &= (z > self.depth_range[0]) & (z < self.depth_range[1])
            good &= np.linalg.norm(proj - uv, axis=1) < self.max_reproj_px
            centre = -w2c[:3, :3].T @ w2c[:3, 3]
            rays.append(X - centre)
        cos = (rays[0] * rays[1]).sum(1) / (np.linalg.norm(rays[0], axis=1) * np.linalg.norm(rays[1], axis=1) + 1e-12)
        return good & (np.arccos(np.clip(cos, -1, 1)) > self.min_parallax)

    @staticmethod
    def _colors(rgb: np.ndarray, uv: np.ndarray) -> np.ndarray:
        px = np.clip(np.round(uv).astype(int), 0, [rgb.shape[1] - 1, rgb.shape[0] - 1])
        return rgb[px[:, 1], px[:, 0]].astype(np.float32).reshape(-1, 3)
