"""Parameters of the ORB frontend, grouped as in conf/slam/orb.yaml (defaults = that file's)."""
from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any, Mapping

from segs.errors import ConfigError


@dataclass
class FeatureConfig:
    n_features: int = 1500
    scale_factor: float = 1.2
    n_levels: int = 8
    fast_threshold: int = 20
    min_fast_threshold: int = 7
    floor_fast_threshold: int = 3
    cell_size: int = 30
    oversample: float = 3.0
    grid_cell: float = 16.0

    def problems(self) -> list[tuple[str, str]]:
        """(key, what is wrong) for values the ORB extractor cannot run with."""
        out = []
        for key in ("fast_threshold", "min_fast_threshold", "floor_fast_threshold"):
            if not 1 <= getattr(self, key) <= 255:
                out.append((key, f"a FAST intensity threshold in [1, 255]; got {getattr(self, key)}"))
        if self.n_features < 1:
            out.append(("n_features", f"at least 1 keypoint; got {self.n_features}"))
        return out


@dataclass
class TrackingConfig:
    rgbd_baseline: float = 0.08  # virtual stereo baseline of RGB-D (ORB-SLAM's bf / fx)
    rgbd_depth_noise: float = 0.0015  # RGB-D depth sigma = k z^2 (1/m), Kinect v1; ORB-SLAM: 1 px disparity
    rgbd_retry_depth_noise: float = 0.012  # RGB-D: k of one more try for a frame the model above loses (0: off)
    close_depth_factor: float = 40.0  # "close" points: depth < factor * baseline (ORB-SLAM ThDepth)
    max_depth: float = 10.0  # depths beyond are unknown
    depth_edge_ratio: float = 0.05  # RGB-D: no depth where the 3x3 depth range exceeds this x depth
    min_init_points: int = 500  # keypoints with depth to start an RGB-D / stereo map (<= n_features/3)
    init_wait: int = 10  # frames that wait for min_init_points before min_init_points_late will do
    min_init_points_late: int = 150  # keypoints with depth that start a map after init_wait frames
    window_motion: float = 15.0  # projection radius from the last frame, mono (x scale)
    window_motion_stereo: float = 7.0  # idem, stereo / RGB-D
    window_retry_factor: float = 2.0  # too few matches: searched again with this x the window (ORB-SLAM: 2)
    window_no_velocity_factor: float = 2.0  # no velocity (after a relocalization): x the window
    local_map_th: float = 1.0  # local-map projection radius factor (x 2.5 or 4 x scale)
    local_map_th_rgbd: float = 3.0  # RGB-D: local_map_th x this (ORB-SLAM: th = 3)
    local_map_th_reloc: float = 5.0  # the relocalized frame and the next: x this (ORB-SLAM: th = 5)
    local_map_narrow_cos: float = 0.998  # viewing cosine above this: the narrow radius (RadiusByViewingCos)
    local_map_radius_narrow: float = 2.5  # x local_map_th x level scale, nearly frontal views
    local_map_radius_wide: float = 4.0  # idem, the other views
    local_kfs: int = 40  # keyframes in the local map
    local_map_covisible: int = 10  # best covisible keyframes of each that join the local map (ORB-SLAM: 10)
    min_matches_motion: int = 20
    min_inliers: int = 30  # local-map inliers to call a frame tracked
    min_inliers_reloc: int = 50  # idem, during the frames after a relocalization
    reloc_recent_frames: int = 30  # frames after a relocalization that need min_inliers_reloc
    local_map_ratio: float = 0.8  # nearest / second-nearest descriptor ratio of local-map projection
    ref_match_ratio: float = 0.7  # descriptor ratio matching the reference keyframe (ORB-SLAM: 0.7)
    pnp_match_ratio: float = 0.9  # looser ratio of the matches fed to PnP RANSAC (fallback, relocalization)
    pnp_reproj_factor: float = 2.0  # PnP RANSAC inlier threshold: this x sqrt(chi2 2 dof 95 %) pixels
    min_matches_ref: int = 15  # matches with the reference keyframe needed to try its pose (ORB-SLAM: 15)
    min_pose_inliers: int = 10  # inliers of a motion / reference / PnP pose to accept it (ORB-SLAM: 10)
    kf_max_gap: int = 15  # a keyframe at least every N frames (if c2 holds); authors: 15
    kf_min_gap: int = 3  # ratio-rule keyframes not sooner than this (paces single-thread mode)
    kf_min_gap_mono: int = 5  # idem, monocular
    kf_view_change_deg_mono: float = 3.0  # monocular: ... unless the view changed this much since the newest keyframe
    kf_ref_ratio: float = 0.75  # inliers / reference keyframe's points below this -> keyframe (ORB-SLAM3)
    kf_ref_ratio_mono: float = 0.9
    kf_weak_mono: int = 100  # monocular: a keyframe whenever fewer points are tracked (ORB-SLAM3 c4: 75)
    kf_track_ratio: float = 0.5  # ... or below this share of the best count since the last keyframe
    kf_ref_ratio_weak: float = 0.25  # stereo / RGB-D: a keyframe is needed below this x the reference's (c1c)
    kf_min_tracked: int = 15  # no keyframe from a frame with this many tracked points or fewer (c2, c4)
    kf_close_tracked: int = 100  # stereo / RGB-D: need close points if fewer tracked ...
    kf_close_untracked: int = 70  # ... and more than this untracked
    rgbd_new_points: str = "all"  # "all": every unmatched keypoint with depth; "close": < ThDepth
    kf_min_new_points: int = 100  # "close": at least this many of the nearest anyway (ORB-SLAM: 100)
    reloc_candidates: int = 10
    reloc_min_matches: int = 15
    recent_lost: int = 30  # lost for at most this many frames: try the last reference keyframe first
    recent_lost_covisible: int = 2  # ... and this many of its best covisible keyframes
    restart_after_lost: int = 10  # stereo / RGB-D: frames lost before a new map segment anchored
    # at the last tracked pose (0: never; monocular never restarts: its scale would be unrelated)

    def problems(self) -> list[tuple[str, str]]:
        """(key, what is wrong) for values tracking cannot run with."""
        out = []
        if self.init_wait < 0:
            out.append(("init_wait", f"a number of frames >= 0; got {self.init_wait}"))
        if self.min_init_points_late < 1:  # above min_init_points it has no effect
            out.append(("min_init_points_late", f"at least 1 keypoint; got {self.min_init_points_late}"))
        if not self.rgbd_depth_noise > 0:
            out.append(("rgbd_depth_noise", f"a depth sigma coefficient > 0 (1/m); got {self.rgbd_depth_noise}"))
        if self.rgbd_retry_depth_noise < 0:
            out.append(("rgbd_retry_depth_noise", f">= 0 (0: no retry); got {self.rgbd_retry_depth_noise}"))
        return out


@dataclass
class InitConfig:
    min_matches: int = 100
    min_parallax_deg: float = 1.0  # 50th-largest parallax of the counted matches (ORB-SLAM: 1.0)
    fallback_min_parallax_deg: float = 4.0  # idem, the fundamental matrix after a failed homography (ours)
    min_triangulated: int = 50
    max_frames: int = 60  # frames a reference may wait for its partner before it is replaced
    homography_ratio: float = 0.40  # R_H = S_H / (S_H + S_F) above this -> homography
    ba_iterations: int = 20  # bundle adjustment of the two-view map (ORB-SLAM: 20)
    depth_scale_points: int = 20  # stereo / RGB-D depth-poor start: two views scaled by this many depths (0: off)


@dataclass
class MappingConfig:
    triangulate_neighbors: int = 10  # covisible keyframes to triangulate with (mono: x2)
    fuse_neighbors: int = 10
    fuse_second_neighbors: int = 5  # ... and this many best covisible of each (ORB-SLAM: 5)
    fuse_th: float = 3.0  # projection radius (x level scale) of point fusion (ORB-SLAM: 3)
    triangulate_ratio: float = 0.6
    triangulate_node_level: int = 0  # candidates under one vocabulary node of this level (0: all)
    scale_consistency: float = 1.5  # distance ratio vs octave ratio within this x scale_factor (ratioFactor)
    min_baseline_ratio: float = 0.01  # monocular partners need baseline / median depth above this
    min_parallax_deg: float = 1.15  # rays of a triangulated point (no depth) at least this far apart
    min_parallax_deg_mono: float = 2.0  # idem, monocular (see conf/slam/orb.yaml)
    ba_window: int = 7  # optimised keyframes of local BA (new one + best covisible)
    ba_fixed_max: int = 10  # keyframes held fixed around the window
    ba_iterations: tuple = (4, 1)  # LM iterations before / after removing outliers (0: one pass); mono, stereo
    ba_iterations_rgbd: tuple = (1, 0)  # the same for RGB-D (points start at their measured depth)
    ba_min_gain: float = 0.01  # the first pass stops after an iteration gaining less than this fraction of the cost
    cull_points: bool = True
    min_found_ratio: float = 0.25
    recent_cull_age: int = 2  # keyframes after its creation: a point with few observers is culled ...
    recent_min_obs: int = 3  # ... at most this many (stereo / RGB-D; ORB-SLAM: 3) ...
    recent_min_obs_mono: int = 2  # ... monocular (ORB-SLAM: 2)
    recent_mature_age: int = 3  # keyframes after which a surviving point is mature (reaches the mapper)
    cull_keyframes: bool = True
    redundancy: float = 0.9  # keyframe culled if this share of its points is seen by >=3 others
    cull_window: int = 30  # only among its best covisible keyframes
    redundant_observers: int = 3  # "seen by others": at least this many at the same or a finer scale

    def problems(self) -> list[tuple[str, str]]:
        """(key, what is wrong) for values local BA cannot run with."""
        out = []
        for key in ("ba_iterations", "ba_iterations_rgbd"):
            its = tuple(getattr(self, key))
            if len(its) not in (1, 2) or not all(isinstance(i, int) and i >= 0 for i in its) or its[0] < 1:
                out.append((key, f"[first, second] LM iterations, first >= 1, second >= 0; got {list(its)}"))
        if not 0.0 <= self.ba_min_gain < 1.0:
            out.append(("ba_min_gain", f"a fraction of the cost in [0, 1); got {self.ba_min_gain}"))
        if self.ba_window < 1:
            out.append(("ba_window", f"at least 1 keyframe; got {self.ba_window}"))
        if self.triangulate_node_level < 0:
            out.append(("triangulate_node_level", f"a vocabulary tree level >= 0; got {self.triangulate_node_level}"))
        if self.ba_fixed_max < 0:
            out.append(("ba_fixed_max", f"at least 0 keyframes; got {self.ba_fixed_max}"))
        return out


@dataclass
class LoopConfig:
    enabled: bool = True
    vocabulary: str | None = None  # .npz; None = the shipped one
    min_kfs: int = 10  # keyframes in the map before loops are searched
    consistency: int = 3  # consecutive consistent detections
    min_matches: int = 20  # descriptor matches with a candidate
    match_ratio: float = 0.75  # their nearest / second-nearest descriptor ratio
    min_inliers: int = 20  # RANSAC inliers of the similarity
    min_total: int = 40  # matches after guided search to accept the loop
    ransac_iterations: int = 300  # RANSAC of the loop similarity (minimal sets of 3)
    guided_search_th: float = 10.0  # projection radius (x level scale) of the guided search (ORB-SLAM: 10)
    fuse_th: float = 4.0  # projection radius fusing the loop's points into its neighbours (ORB-SLAM: 4)
    covis_edges: int = 100  # essential graph: covisibility edges with this weight
    pose_graph_iterations: int = 20
    global_ba: bool = True
    global_ba_iterations: int = 10
    min_gap_kfs: int = 10  # a loop partner must be this many keyframes older
    min_kfs_since_loop: int = 10  # keyframes after a closed loop before the next search


@dataclass
class MatchingConfig:
    """Projection searches of map points into frames and keyframes (ORB-SLAM's isInFrustum / Fuse)."""

    dist_margin_min: float = 0.8  # searched from distances >= this x its scale-invariance minimum
    dist_margin_max: float = 1.2  # ... and <= this x its maximum (ORB-SLAM: 0.8 / 1.2)
    min_view_cos: float = 0.5  # viewing ray vs the point's mean viewing direction: cosine >= this


GROUPS = {"features": FeatureConfig, "tracking": TrackingConfig, "init": InitConfig,
          "mapping": MappingConfig, "loop": LoopConfig, "matching": MatchingConfig}


def build(cls, values: Mapping[str, Any] | None, where: str):
    """Dataclass `cls` from a mapping (dict or OmegaConf), unknown keys -> ConfigError."""
    values = dict(values or {})
    names = {f.name: f for f in fields(cls)}
    unknown = sorted(set(values) - set(names))
    if unknown:
        raise ConfigError(f"slam.{where}: unknown key(s) {', '.join(unknown)}; known: {', '.join(names)}")
    out = {}
    for k, v in values.items():
        if hasattr(v, "__iter__") and not isinstance(v, (str, bytes)) and not hasattr(v, "items"):
            v = tuple(v)
        out[k] = v
    cfg = cls(**out)
    problems = cfg.problems() if hasattr(cfg, "problems") else []
    if problems:
        key, why = problems[0]
        raise ConfigError(f"slam.{where}.{key}: {why}")
    return cfg
