"""Per-tile point budgets that sum exactly to round(ratio * N), by the largest-remainder method."""
from __future__ import annotations

import numpy as np


def target_count(ratio: float, total: int) -> int:
    """round(ratio * N) with halves rounded up (not Python's banker's rounding)."""
    return min(total, int(np.floor(ratio * total + 0.5)))


def tile_budgets(counts: np.ndarray, ratio: float, floors: np.ndarray | None = None) -> np.ndarray:
    """Integer budgets <= counts summing to target_count(ratio, counts.sum()): proportional to the counts,
    but never below a tile's floor (e.g. one point per occupied plan cell, so a sparse tile keeps its area).

    Quotas are max(floor, c * count) with c chosen so they sum to the target (floors scaled down if
    they alone exceed it); integers by the largest-remainder method, ties to the lower tile id.
    """
    counts = np.asarray(counts, dtype=np.int64)
    target = target_count(ratio, int(counts.sum()))
    floors = np.zeros_like(counts) if floors is None else np.minimum(np.asarray(floors, dtype=np.int64), counts)
    if floors.sum() >= target:
        return largest_remainder(floors * (target / max(int(floors.sum()), 1)), floors, target)
    bound = np.zeros(len(counts), dtype=bool)  # tiles held at their floor
    while True:
        free = ~bound
        scale = (target - floors[bound].sum()) / max(int(counts[free].sum()), 1)
        newly = free & (scale * counts < floors)
        if not newly.any():
            break
        bound |= newly
    quotas = np.where(bound, floors, counts * scale)
    return largest_remainder(quotas, counts, target, minimum=floors)


def largest_remainder(quotas: np.ndarray, caps: np.ndarray, target: int, minimum: np.ndarray | None = None) -> np.ndarray:
    """Integers near `quotas`, within [minimum, caps], summing to `target`: floors first, then one more each
    to the largest remainders (stable: ties to the lower index)."""
    budgets = np.minimum(np.floor(quotas + 1e-9).astype(np.int64), caps)
    if minimum is not None:
        budgets = np.maximum(budgets, np.minimum(minimum, caps))
    short = target - int(budgets.sum())
    order = np.argsort(-(quotas - budgets), kind="stable")
    order = order[budgets[order] < caps[order]]
    budgets[order[:short]] += 1
    return budgets
