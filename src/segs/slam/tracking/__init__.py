"""Per frame: tracking (`Tracker`: pose, local map, keyframe decision, relocalization), map
initialization and the per-frame pose record (`FramePoses`)."""
