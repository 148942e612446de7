"""Parameters of the SLAM frontends: the ORB frontend's groups as in conf/slam/orb.yaml and the
known-poses frontend's keys (conf/slam/known_poses.yaml).

Every value is written once, in those YAML files (where each is documented): the dataclasses have
no defaults, so a key missing from a config is an error, never a second default. `slam_config`
builds the `slam` node with segs.schema.build (an unknown or missing key, or a value of the wrong
kind, is one line naming the full key: `slam.tracking.min_inlier: unknown key`), then checks the
ranges (`problems()`)."""
from __future__ import annotations

from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, Mapping

from segs import schema
from segs.errors import ConfigError


@dataclass
class FeatureConfig:
    n_features: int
    scale_factor: float
    n_levels: int
    fast_threshold: int
    min_fast_threshold: int
    floor_fast_threshold: int
    cell_size: int
    oversample: float
    grid_cell: float

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
    rgbd_baseline: float  # virtual stereo baseline of RGB-D (ORB-SLAM's bf / fx)
    rgbd_depth_noise: float  # RGB-D depth sigma = k z^2 (1/m), Kinect v1; ORB-SLAM: 1 px disparity
    rgbd_retry_depth_noise: float  # RGB-D: k of one more try for a frame the model above loses (0: off)
    close_depth_factor: float  # "close" points: depth < factor * baseline (ORB-SLAM ThDepth)
    max_depth: float  # depths beyond are unknown
    depth_edge_ratio: float  # RGB-D: no depth where the 3x3 depth range exceeds this x depth
    min_init_points: int  # keypoints with depth to start an RGB-D / stereo map (<= n_features/3)
    init_wait: int  # frames that wait for min_init_points before min_init_points_late will do
    min_init_points_late: int  # keypoints with depth that start a map after init_wait frames
    window_motion: float  # projection radius from the last frame, mono (x scale)
    window_motion_stereo: float  # idem, stereo / RGB-D
    window_retry_factor: float  # too few matches: searched again with this x the window (ORB-SLAM: 2)
    window_no_velocity_factor: float  # no velocity (after a relocalization): x the window
    local_map_th: float  # local-map projection radius factor (x 2.5 or 4 x scale)
    local_map_th_rgbd: float  # RGB-D: local_map_th x this (ORB-SLAM: th = 3)
    local_map_th_reloc: float  # the relocalized frame and the next: x this (ORB-SLAM: th = 5)
    local_map_narrow_cos: float  # viewing cosine above this: the narrow radius (RadiusByViewingCos)
    local_map_radius_narrow: float  # x local_map_th x level scale, nearly frontal views
    local_map_radius_wide: float  # idem, the other views
    local_kfs: int  # keyframes in the local map
    local_map_covisible: int  # best covisible keyframes of each that join the local map (ORB-SLAM: 10)
    min_matches_motion: int
    min_inliers: int  # local-map inliers to call a frame tracked
    min_inliers_reloc: int  # idem, during the frames after a relocalization
    reloc_recent_frames: int  # frames after a relocalization that need min_inliers_reloc
    local_map_ratio: float  # nearest / second-nearest descriptor ratio of local-map projection
    ref_match_ratio: float  # descriptor ratio matching the reference keyframe (ORB-SLAM: 0.7)
    pnp_match_ratio: float  # looser ratio of the matches fed to PnP RANSAC (fallback, relocalization)
    pnp_reproj_factor: float  # PnP RANSAC inlier threshold: this x sqrt(chi2 2 dof 95 %) pixels
    min_matches_ref: int  # matches with the reference keyframe needed to try its pose (ORB-SLAM: 15)
    min_pose_inliers: int  # inliers of a motion / reference / PnP pose to accept it (ORB-SLAM: 10)
    kf_max_gap: int  # a keyframe at least every N frames (if c2 holds); authors: 15
    kf_min_gap: int  # ratio-rule keyframes not sooner than this (paces single-thread mode)
    kf_min_gap_mono: int  # idem, monocular
    kf_view_change_deg_mono: float  # monocular: ... unless the view changed this much since the newest keyframe
    kf_ref_ratio: float  # inliers / reference keyframe's points below this -> keyframe (ORB-SLAM3)
    kf_ref_ratio_mono: float
    kf_weak_mono: int  # monocular: a keyframe whenever fewer points are tracked (ORB-SLAM3 c4: 75)
    kf_track_ratio: float  # ... or below this share of the best count since the last keyframe
    kf_ref_ratio_weak: float  # stereo / RGB-D: a keyframe is needed below this x the reference's (c1c)
    kf_min_tracked: int  # no keyframe from a frame with this many tracked points or fewer (c2, c4)
    kf_close_tracked: int  # stereo / RGB-D: need close points if fewer tracked ...
    kf_close_untracked: int  # ... and more than this untracked
    rgbd_new_points: str  # "all": every unmatched keypoint with depth; "close": < ThDepth
    kf_min_new_points: int  # "close": at least this many of the nearest anyway (ORB-SLAM: 100)
    reloc_candidates: int
    reloc_min_matches: int
    recent_lost: int  # lost for at most this many frames: try the last reference keyframe first
    recent_lost_covisible: int  # ... and this many of its best covisible keyframes
    restart_after_lost: int  # stereo / RGB-D: frames lost before a new map segment anchored
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
    min_matches: int
    min_parallax_deg: float  # 50th-largest parallax of the counted matches (ORB-SLAM: 1.0)
    fallback_min_parallax_deg: float  # idem, the fundamental matrix after a failed homography (ours)
    min_triangulated: int
    max_frames: int  # frames a reference may wait for its partner before it is replaced
    homography_ratio: float  # R_H = S_H / (S_H + S_F) above this -> homography
    ba_iterations: int  # bundle adjustment of the two-view map (ORB-SLAM: 20)
    depth_scale_points: int  # stereo / RGB-D depth-poor start: two views scaled by this many depths (0: off)


@dataclass
class LocalMappingConfig:
    triangulate_neighbors: int  # covisible keyframes to triangulate with (mono: x2)
    fuse_neighbors: int
    fuse_second_neighbors: int  # ... and this many best covisible of each (ORB-SLAM: 5)
    fuse_th: float  # projection radius (x level scale) of point fusion (ORB-SLAM: 3)
    triangulate_ratio: float
    triangulate_node_level: int  # candidates under one vocabulary node of this level (0: all)
    scale_consistency: float  # distance ratio vs octave ratio within this x scale_factor (ratioFactor)
    min_baseline_ratio: float  # monocular partners need baseline / median depth above this
    min_parallax_deg: float  # rays of a triangulated point (no depth) at least this far apart
    min_parallax_deg_mono: float  # idem, monocular (see conf/slam/orb.yaml)
    ba_window: int  # optimised keyframes of local BA (new one + best covisible)
    ba_fixed_max: int  # keyframes held fixed around the window
    ba_iterations: tuple  # LM iterations before / after removing outliers (0: one pass); mono, stereo
    ba_iterations_rgbd: tuple  # the same for RGB-D (points start at their measured depth)
    ba_min_gain: float  # the first pass stops after an iteration gaining less than this fraction of the cost
    cull_points: bool
    min_found_ratio: float
    recent_cull_age: int  # keyframes after its creation: a point with few observers is culled ...
    recent_min_obs: int  # ... at most this many (stereo / RGB-D; ORB-SLAM: 3) ...
    recent_min_obs_mono: int  # ... monocular (ORB-SLAM: 2)
    recent_mature_age: int  # keyframes after which a surviving point is mature (reaches the mapper)
    cull_keyframes: bool
    redundancy: float  # keyframe culled if this share of its points is seen by >=3 others
    cull_window: int  # only among its best covisible keyframes
    redundant_observers: int  # "seen by others": at least this many at the same or a finer scale

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
    enabled: bool
    vocabulary: str | None  # .npz; None = the shipped one
    min_kfs: int  # keyframes in the map before loops are searched
    consistency: int  # consecutive consistent detections
    min_matches: int  # descriptor matches with a candidate
    match_ratio: float  # their nearest / second-nearest descriptor ratio
    min_inliers: int  # RANSAC inliers of the similarity
    min_total: int  # matches after guided search to accept the loop
    ransac_iterations: int  # RANSAC of the loop similarity (minimal sets of 3)
    guided_search_th: float  # projection radius (x level scale) of the guided search (ORB-SLAM: 10)
    fuse_th: float  # projection radius fusing the loop's points into its neighbours (ORB-SLAM: 4)
    covis_edges: int  # essential graph: covisibility edges with this weight
    pose_graph_iterations: int
    global_ba: bool
    global_ba_iterations: int
    min_gap_kfs: int  # a loop partner must be this many keyframes older
    min_kfs_since_loop: int  # keyframes after a closed loop before the next search


@dataclass
class MatchingConfig:
    """Projection searches of map points into frames and keyframes (ORB-SLAM's isInFrustum / Fuse)."""

    dist_margin_min: float  # searched from distances >= this x its scale-invariance minimum
    dist_margin_max: float  # ... and <= this x its maximum (ORB-SLAM: 0.8 / 1.2)
    min_view_cos: float  # viewing ray vs the point's mean viewing direction: cosine >= this


# the ORB frontend's groups (conf/slam/orb.yaml), in the order of the file
GROUPS = {"features": FeatureConfig, "tracking": TrackingConfig, "init": InitConfig,
          "local_mapping": LocalMappingConfig, "loop": LoopConfig, "matching": MatchingConfig}


@dataclass
class OrbConfig:
    """The `slam` node of segs.slam.orb.OrbFrontend (conf/slam/orb.yaml)."""

    threaded: bool
    seed: int
    final_global_ba: bool
    verbose: bool
    features: FeatureConfig
    tracking: TrackingConfig
    init: InitConfig
    local_mapping: LocalMappingConfig
    loop: LoopConfig
    matching: MatchingConfig


@dataclass
class KnownPosesConfig:
    """The `slam` node of segs.slam.known_poses.KnownPosesFrontend (conf/slam/known_poses.yaml)."""

    keyframe_every: int
    kf_translation: float
    kf_rotation_deg: float
    n_features: int
    fast_threshold: int
    depth_range: tuple
    max_reproj_px: float
    min_parallax_deg: float
    stereo_num_disparities: int
    max_hamming: int
    point_source: str
    grid_stride: int


# the `slam` node's _target_ -> its dataclass
FRONTENDS = {"segs.slam.orb.OrbFrontend": OrbConfig, "segs.slam.known_poses.KnownPosesFrontend": KnownPosesConfig}
HYDRA_KEYS = ("_target_", "_partial_")
RENAMED = {"mapping": "slam.local_mapping"}  # the ORB frontend's local mapping group, before it was renamed


def slam_config(values: Mapping[str, Any]) -> OrbConfig | KnownPosesConfig:
    """The typed `slam` node (a dict or OmegaConf node with its _target_); ConfigError of one
    line naming the full key for an unknown / missing key, a value of the wrong kind or out of range."""
    target = values.get("_target_")
    cls = FRONTENDS.get(target)
    if cls is None:
        raise ConfigError(f"slam._target_={target!r}: not a frontend; known: {', '.join(FRONTENDS)}")
    return build_frontend_config(cls, {k: v for k, v in values.items() if k not in HYDRA_KEYS})


def build_frontend_config(cls: type, values: Mapping[str, Any]):
    """`cls` (OrbConfig or KnownPosesConfig) from the slam node's keys, ranges checked."""
    cfg = schema.build(cls, values, "slam", renamed=RENAMED)
    for name in (f.name for f in fields(cfg)):
        _check(getattr(cfg, name), f"slam.{name}")
    return cfg


def _check(group, where: str) -> None:
    """ConfigError for the first value of a group out of its range."""
    for key, why in group.problems() if hasattr(group, "problems") else ():
        raise ConfigError(f"{where}.{key}: {why}")


# where the ORB frontend's groups are written (the vocabulary trainer reads its `features`)
ORB_YAML = Path(__file__).resolve().parents[3] / "conf" / "slam" / "orb.yaml"


def group_from_yaml(name: str, **overrides):
    """The typed group `name` of conf/slam/orb.yaml with keys overridden (the vocabulary
    trainer, tests): group_from_yaml("features", n_features=300)."""
    import yaml

    values = {**yaml.safe_load(ORB_YAML.read_text())[name], **overrides}
    cfg = schema.build(GROUPS[name], values, f"slam.{name}")
    _check(cfg, f"slam.{name}")
    return cfg
