"""The state every stage shares: the map of keyframes and points (`Map`, one RLock), the
bag-of-words vocabulary and the keyframe database (`vocab/`: the shipped vocabulary)."""
