"""Tile plan, out-of-core bucketing, per-tile budgets and the seam-aware stitch."""
