"""Per keyframe: the keyframe queue (inline or the mapping thread), local mapping (triangulation,
fusion, local bundle adjustment, culling), loop closing, and bundle adjustment in a child process."""
