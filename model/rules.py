"""Rules the whole project shares, written once: how many points a ratio keeps, and how coordinates sit on
a LAS grid (integers times scale plus offset). model, tiling and pipeline all import this module; it
imports nothing of theirs."""
from __future__ import annotations

import numpy as np


def kept_count(ratio: float, total: int) -> int:
    """round(ratio * N) with halves rounded up (not Python's banker's rounding), at most N."""
    return min(total, int(np.floor(ratio * total + 0.5)))


def grid_xyz(records: np.ndarray, scales: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """(n, 3) float64 coordinates of (n,) LAS records: their integer X/Y/Z times (3,) scales plus offsets."""
    ints = np.column_stack([records["X"], records["Y"], records["Z"]]).astype(np.float64)
    return ints * scales + offsets


def grid_ints(xyz: np.ndarray, scales: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """(n, 3) float64 integers of the grid steps nearest to (n, 3) coordinates (before any int32 check)."""
    return np.rint((xyz - offsets) / scales)
