"""segs.slam: the SLAM frontends behind `base.Frontend` (the ORB-SLAM style `orb.OrbFrontend`, the
ground-truth `known_poses.KnownPosesFrontend`). The ORB frontend's stages, in the order a frame
meets them: features/ (per frame, ahead of tracking), tracking/ (per frame), backend/ (per
keyframe: local mapping, loop closing); shared by them: map/, estimation/ (matching, optimisation),
native/ (C++ kernels) and the modules here (config, sensor, geometry, state, outbox). The frame
loops around any Frontend are segs.pipeline's."""
