"""What the report and `compare` draw: kept-to-expected density maps, metric plots, the 3-D before/after
view of one region and the report's tables."""
