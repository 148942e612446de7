"""Shared by tracking and the backend: ORB matching (data association of keypoints and map points)
and optimisation (motion-only pose refinement, PnP, bundle adjustment, pose graph)."""
