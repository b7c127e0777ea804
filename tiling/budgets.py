"""Per-tile point budgets that sum exactly to round(ratio * N), by the largest-remainder method."""
from __future__ import annotations

import numpy as np


def target_count(ratio: float, total: int) -> int:
    """round(ratio * N) with halves rounded up (not Python's banker's rounding)."""
    return min(total, int(np.floor(ratio * total + 0.5)))


def tile_budgets(counts: np.ndarray, ratio: float) -> np.ndarray:
    """Integer budgets <= counts, proportional to them, summing to target_count(ratio, counts.sum())."""
    counts = np.asarray(counts, dtype=np.int64)
    target = target_count(ratio, int(counts.sum()))
    quotas = counts * (target / max(int(counts.sum()), 1))
    budgets = np.minimum(np.floor(quotas).astype(np.int64), counts)
    short = target - int(budgets.sum())
    # ties in the remainders go to the lower tile id (stable sort), so the result is deterministic
    order = np.argsort(-(quotas - budgets), kind="stable")
    order = order[budgets[order] < counts[order]]
    budgets[order[:short]] += 1
    return budgets
