"""segs.data."""
