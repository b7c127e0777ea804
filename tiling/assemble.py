"""The stitch: finished tiles' kept points become each output level's parts, tile by tile.

Seams are resolved once, for the finest level (tiling.stitch); a coarser level takes each tile's first
points of the same accepted order, so every level is a subset of the one before and none has seam
duplicates. Points a class rule keeps whole are in every level, spread through the part's order.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from model.rules import column_max, column_min, grid_ints, grid_xyz, interleaved, spread_order, take_records
from tiling.plan import TilePlan
from tiling.stitch import SeamBand, band_mask, first_accepted, resolve_seams


@dataclass(frozen=True)
class TilePart:
    """One tile's kept points, in output order, and their XY bounds (the core rectangle, grown to hold them):
    what every output writer receives."""

    tile_id: int
    bounds: tuple[float, float, float, float]
    records: np.ndarray


@dataclass(frozen=True)
class TileResult:
    """A finished tile: (n,) candidate records and (n, 3) xyz in priority order, and the (w,) records and
    (w, 3) xyz of the core points it keeps whole."""

    records: np.ndarray
    xyz: np.ndarray
    whole: np.ndarray
    whole_xyz: np.ndarray

    @classmethod
    def load(cls, path: str | Path) -> "TileResult":
        """Read a result saved by pipeline.engine.tasks.simplify_tile."""
        with np.load(path) as saved:
            return cls(saved["records"], saved["xyz"], saved["whole"], saved["whole_xyz"])

    @staticmethod
    def load_xyz(path: str | Path) -> np.ndarray:
        """The (n, 3) candidates' positions only: the seam pass needs no records (they are read once, to write)."""
        with np.load(path) as saved:
            return saved["xyz"]


def seam_rejections(plan: TilePlan, results: dict[int, str], budgets: np.ndarray, tolerance: float,
                    on_tile: Callable[[], None] = lambda: None) -> dict[int, np.ndarray]:
    """Candidate ranks each tile gives up so no two kept points of different tiles are closer than
    `tolerance`; only candidates near a tile's border are held in memory. `on_tile` hears each tile read."""
    bands, candidate_counts = [], np.zeros(len(plan.tiles), dtype=np.int64)
    for tile_id, path in sorted(results.items()):
        on_tile()
        xyz = TileResult.load_xyz(path)
        candidate_counts[tile_id] = len(xyz)
        near = np.flatnonzero(band_mask(xyz, plan.bounds(tile_id), tolerance))
        bands.append(SeamBand(tile_id, near, xyz[near]))
    return resolve_seams(bands, candidate_counts, budgets, tolerance)


def level_parts(plan: TilePlan, results: dict[int, str], budgets: np.ndarray, level_budgets: np.ndarray,
                rejections: dict[int, np.ndarray], scales: np.ndarray,
                offsets: np.ndarray) -> Iterator[TilePart]:
    """One level's parts in tile order: each tile's first `level_budgets` accepted candidates (of the
    `budgets` the finest level keeps) and every point it keeps whole; one tile in memory at a time. A
    refined point is written on the scan's grid of (3,) `scales` and `offsets`."""
    for tile_id, path in sorted(results.items()):
        result = TileResult.load(path)
        rejected = rejections.get(tile_id, np.empty(0, dtype=np.int64))
        chosen = first_accepted(len(result.records), int(budgets[tile_id]), rejected)[:int(level_budgets[tile_id])]
        records = np.concatenate([moved_to(take_records(result.records, chosen), result.xyz[chosen], scales, offsets,
                                           picked_box(result.records, scales, offsets)), result.whole])
        order = interleaved(np.arange(len(chosen)), len(chosen) + spread_order(result.whole_xyz))
        records = take_records(records, order)
        yield TilePart(tile_id, covering(plan.bounds(tile_id), grid_xyz(records, scales, offsets)), records)


def covering(rect: tuple[float, float, float, float], xyz: np.ndarray) -> tuple[float, float, float, float]:
    """The tile's core rectangle grown to hold its kept points: a refined point may move slightly outside."""
    if len(xyz) == 0:
        return rect
    low, high = column_min(xyz[:, :2]), column_max(xyz[:, :2])
    return (min(rect[0], float(low[0])), min(rect[1], float(low[1])),
            max(rect[2], float(high[0])), max(rect[3], float(high[1])))


def picked_box(records: np.ndarray, scales: np.ndarray, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(3,) low and high corners of the measured positions of a tile's picks (records, before any refinement)."""
    xyz = grid_xyz(records, scales, offsets)
    return (column_min(xyz), column_max(xyz)) if len(xyz) else (np.zeros(3), np.zeros(3))


def moved_to(records: np.ndarray, xyz: np.ndarray, scales: np.ndarray, offsets: np.ndarray,
             box: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """(n,) records whose X/Y/Z follow (n, 3) xyz where a method refined the position (attributes stay the
    source's), held inside `box`, the corners of the tile's picks as measured: the paper's refinement moves
    points in a unit ball scaled by the tile's largest side, so a tall or thin tile's points left it (a plane
    for metres off it, a 10 km tower by 300 m), and a point pushed past the grid's int32 reach wrapped to the
    far side of the scan."""
    moved = np.any(xyz != grid_xyz(records, scales, offsets), axis=1)
    if moved.any():
        ints = grid_ints(np.clip(xyz[moved], *box), scales, offsets).astype(np.int32)
        for axis, name in enumerate("XYZ"):
            records[name][moved] = ints[:, axis]
    return records
