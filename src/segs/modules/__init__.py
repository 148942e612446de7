"""segs.modules."""
