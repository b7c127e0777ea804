"""Rules the whole project shares, written once: how many points a ratio keeps, how coordinates sit on a
LAS grid (integers times scale plus offset), the bounds of narrow arrays, and the orders that make any
prefix of a selection spread out (a Z-order curve, bit-reversed rank). model, tiling and pipeline all
import this module; it imports nothing of theirs (tiling imports nothing else of model)."""
from __future__ import annotations

import numpy as np


def kept_count(ratio: float, total: int) -> int:
    """round(ratio * N) with halves rounded up (not Python's banker's rounding), at most N."""
    return min(total, int(np.floor(ratio * total + 0.5)))


def grid_xyz(records: np.ndarray, scales: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """(n, 3) float64 coordinates of (n,) LAS records: their integer X/Y/Z times (3,) scales plus offsets,
    a column at a time (the same values as broadcasting over an (n, 3) copy of the integers, 5x faster)."""
    xyz = np.empty((len(records), 3), dtype=np.float64)
    for axis, name in enumerate("XYZ"):
        np.multiply(records[name], scales[axis], out=xyz[:, axis])
        xyz[:, axis] += offsets[axis]
    return xyz


def record_bytes(records: np.ndarray) -> np.ndarray:
    """(n, itemsize) uint8: each of (n,) structured records as its raw bytes, a view where they are contiguous."""
    return np.ascontiguousarray(records).view(np.uint8).reshape(len(records), records.dtype.itemsize)


def take_records(records: np.ndarray, index: np.ndarray) -> np.ndarray:
    """records[index] for (n,) structured LAS records and (m,) integer positions (not a mask), each record's
    bytes gathered whole: the structured array's own fancy index copies field by field (300k of bcts_1's
    records: 84-113 ms, this way 12-38)."""
    return np.take(record_bytes(records), index, axis=0).view(records.dtype).reshape(-1)


def grid_ints(xyz: np.ndarray, scales: np.ndarray | float, offsets: np.ndarray | float) -> np.ndarray:
    """(n, 3) float64 integers of the grid steps nearest to (n, 3) coordinates (before any int32 check), or
    (n,) of one axis' coordinates with its scale and offset: rint((xyz - offsets) / scales), as laspy's scaled
    assignment rounds, worked out in place on one float64 copy."""
    steps = np.subtract(xyz, offsets, dtype=np.float64)
    np.divide(steps, scales, out=steps)
    return np.rint(steps, out=steps)


def column_min(values: np.ndarray) -> np.ndarray:
    """(d,) the least value of each column of (n, d) `values`: values.min(axis=0), exactly, but a column at
    a time (numpy 2.4 reduces a narrow array along axis 0 about 10x slower: 2.0 against 0.2 ms for 45k x 3)."""
    return np.array([values[:, column].min() for column in range(values.shape[1])], dtype=values.dtype)


def column_max(values: np.ndarray) -> np.ndarray:
    """(d,) the greatest value of each column of (n, d) `values`: values.max(axis=0), exactly."""
    return np.array([values[:, column].max() for column in range(values.shape[1])], dtype=values.dtype)


def column_mean(values: np.ndarray) -> np.ndarray:
    """(d,) the mean of each column of (n, d) float64 `values`: values.mean(axis=0) bit for bit (that reduction
    adds the rows one after another, as a running sum of each column does), 1.6x faster on a (31k, 3) tile."""
    return np.array([np.cumsum(values[:, column])[-1] for column in range(values.shape[1])]) / len(values)


def sorted_distinct(keys: np.ndarray) -> np.ndarray:
    """The distinct values of (n,) integer keys, ascending: a sort and one comparison. numpy 2.4's
    np.unique hashes or argsorts, 3-16x slower on a tile's voxel keys."""
    return distinct_of_sorted(np.sort(keys))


def distinct_count(keys: np.ndarray) -> int:
    """len(sorted_distinct(keys)), without gathering the distinct values."""
    ordered = np.sort(keys)
    return int(np.count_nonzero(ordered[1:] != ordered[:-1])) + 1 if len(ordered) else 0


def distinct_of_sorted(ordered: np.ndarray) -> np.ndarray:
    """The distinct values of (n,) ascending keys, in one comparison."""
    distinct = np.ones(len(ordered), dtype=bool)
    distinct[1:] = ordered[1:] != ordered[:-1]
    return ordered[distinct]


def voxel_edge_for(counts: np.ndarray, sizes: np.ndarray, target: int) -> float:
    """The voxel edge at which points that occupy (levels,) `counts` voxels at ascending edges `sizes`
    occupy `target` (log-log interpolated, held at the ends): counts fall about as a power of the edge."""
    log_counts = np.log(np.maximum(np.asarray(counts, dtype=np.float64), 1))
    return float(np.exp(np.interp(-np.log(max(target, 1)), -log_counts, np.log(sizes))))  # interp wants ascending x


def _spread_bits(values: np.ndarray) -> np.ndarray:
    """Put bit i of each 21-bit integer at bit 3i, for interleaving three coordinates."""
    v = values.astype(np.uint64) & np.uint64(0x1FFFFF)
    for shift, mask in ((32, 0x1F00000000FFFF), (16, 0x1F0000FF0000FF), (8, 0x100F00F00F00F00F),
                        (4, 0x10C30C30C30C30C3), (2, 0x1249249249249249)):
        v = (v | v << np.uint64(shift)) & np.uint64(mask)
    return v


MORTON_STEPS = 2**21  # cells per axis a 63-bit Z-order code tells apart


def morton_codes(cells: np.ndarray) -> np.ndarray:
    """(n,) uint64 Z-order codes of (n, 3) non-negative integer cells below MORTON_STEPS per axis (z's bit
    highest of each triple): code >> 3 is the code of the cells halved, so sorted codes stay sorted."""
    return _spread_bits(cells[:, 0]) | _spread_bits(cells[:, 1]) << np.uint64(1) | _spread_bits(cells[:, 2]) << np.uint64(2)


def morton_order(xyz: np.ndarray) -> np.ndarray:
    """Indices sorting points along a Z-order curve over their bounding cube (2**21 steps per axis)."""
    low = column_min(xyz)
    span = max(float((column_max(xyz) - low).max()), 1e-300)
    return stable_argsort(morton_codes(((xyz - low) * ((MORTON_STEPS - 1) / span)).astype(np.uint64)))


def stable_argsort(keys: np.ndarray) -> np.ndarray:
    """np.argsort(keys, kind="stable") (equal keys in index order), from numpy's default sort, which is
    vectorised (58k uint64 Morton codes: 1.7 against 8.1 ms), and equal keys put back in index order
    afterwards: cheap where they are few, as a curve's codes are (only points within 2**-21 of the extent
    of each other share one)."""
    order = np.argsort(keys)
    ranked = keys[order]
    tied = np.flatnonzero(ranked[1:] == ranked[:-1])
    if len(tied):
        runs = np.union1d(tied, tied + 1)  # positions in runs of equal keys
        order[runs] = order[runs[np.lexsort((order[runs], ranked[runs]))]]
    return order


HASH_FACTORS = np.array([0x9E3779B97F4A7C15, 0xC2B2AE3D27D4EB4F, 0x165667B19E3779F9, 0x27D4EB2F165667C5],
                        dtype=np.uint64)  # odd 64-bit mixing constants (golden ratio, xxHash primes)


def position_keys(xyz: np.ndarray) -> np.ndarray:
    """(n,) uint64 hashes of the (n, d) points' float64 coordinates: equal for exact twins, and for other points
    only by a collision."""
    bits = np.ascontiguousarray(xyz, dtype=np.float64).view(np.uint64)
    key = np.zeros(len(bits), dtype=np.uint64)
    for column in range(bits.shape[1]):
        if column >= 3:  # stir between columns, so equal values in two columns cannot cancel
            key *= HASH_FACTORS[3]
        key ^= bits[:, column] * HASH_FACTORS[column % 3]  # integer products wrap: a hash, not a value
    return key


def most_twins(xyz: np.ndarray) -> int:
    """How many of the (n, d) points share the most shared position, or more where hashes collide (0 for no
    points): a sort of their keys, 0.2 ms for 22k points, so a caller can keep its plain path for a cloud
    without large groups of exact twins."""
    if len(xyz) == 0:
        return 0
    key = np.sort(position_keys(xyz))
    starts = np.flatnonzero(np.concatenate([[True], key[1:] != key[:-1], [True]]))
    return int(np.diff(starts).max())


def identical_runs(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """An (n,) order of the (n, d) points that puts exact twins (the same coordinates) side by side, and (n,)
    bool: where a run of twins starts in that order. Sorted by position_keys (6x faster than np.unique over
    rows on 100k points), a run starts wherever the row changes, so a hash collision can split a position's
    twins into several runs (never join two positions)."""
    key = position_keys(xyz)
    order = np.argsort(key, kind="stable")
    ordered_key, ordered_xyz = key[order], xyz[order]
    starts = np.ones(len(order), dtype=bool)
    starts[1:] = (ordered_key[1:] != ordered_key[:-1]) | np.any(ordered_xyz[1:] != ordered_xyz[:-1], axis=1)
    return order, starts


def capped_twins(xyz: np.ndarray, cap: int) -> np.ndarray:
    """Ascending indices of the (n, d) points but for exact twins past the first `cap` at a position (by index)."""
    order, starts = identical_runs(xyz)
    run_start = np.maximum.accumulate(np.where(starts, np.arange(len(order)), 0))
    return np.sort(order[np.arange(len(order)) - run_start < cap])  # each point's place among its twins


def radical_inverse_order(count: int) -> np.ndarray:
    """A permutation of range(count) by bit-reversed index: every prefix is spread evenly over the range."""
    if count <= 1:
        return np.arange(count, dtype=np.int64)
    bits = int(np.ceil(np.log2(count)))
    index = np.arange(count, dtype=np.uint64)
    reversed_bits = np.zeros(count, dtype=np.uint64)
    for bit in range(bits):
        reversed_bits |= ((index >> np.uint64(bit)) & np.uint64(1)) << np.uint64(bits - 1 - bit)
    return np.argsort(reversed_bits)  # distinct keys: every sort gives this order


def interleaved(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """Two priority orders merged by relative rank (i / len), so any prefix holds each in proportion."""
    rank = np.concatenate([np.arange(len(first)) / max(len(first), 1), np.arange(len(second)) / max(len(second), 1)])
    return np.concatenate([first, second])[np.argsort(rank, kind="stable")]


def spread_order(xyz: np.ndarray, offset: int = 0) -> np.ndarray:
    """(n,) a progressive order of (n, 3) points: along a Z-order curve (started `offset` points in, so a
    seed can vary it) by bit-reversed rank, so any prefix is spread over them."""
    if len(xyz) == 0:
        return np.empty(0, dtype=np.int64)
    return np.roll(morton_order(xyz), -offset)[radical_inverse_order(len(xyz))]
