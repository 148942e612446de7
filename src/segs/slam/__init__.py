"""segs.slam."""
