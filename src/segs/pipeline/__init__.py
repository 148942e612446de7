"""The runtime between SLAM and mapping: the frame loops around any `segs.slam.base.Frontend`."""
