"""The work Dask workers do: bucket a piece into the store (counting its density), copy its rows in crowded
cells sorted by sub-cell, survey a tile, simplify a tile.

Each function takes plain picklable data and touches only its own piece or tile, so any worker of a
local or remote cluster can run it, in any order, with the same result.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, replace
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from model.chamfer_bound import core_sample, fill_gaps, mean_square_distance
from model.cover import counts_within, cover_counts, sampled_cover
from model.methods import Fill, Method
from model.rules import column_mean, column_min, grid_xyz, kept_count, take_records
from model.selection import FillContext, FillLoss, Selection, Tile, VoxelCounts
from model.stratified import pick_spacings, trial_fill
from pipeline.engine.classes import ClassRule, class_histogram
from pipeline.engine.workdir import BucketedPiece, WorkDir, save_npz, write_atomically
from tiling.bucket import SubCellIndex, bucket_by_cell, bucket_by_sub_cell
from tiling.budgets import occupied_voxels, radius_grid
from tiling.plan import DensityGrid, TilePlan
from tiling.store import Slice, StoredPoints, TileStore

SURVEY_PICKS = 1.5  # a survey's farthest point picks over its tile's share of the count: on a surface they cover
# at 0.82x its share's radius. Half a scan's tiles need more than their share at the one radius of the run's
# reference; bcts at 0.1 left 90 / 48 / 5 of 91 tiles to count again with 1 / 1.25 / 1.5 (the run 30 % slower with
# 1), and 1.5 did not move a survey's time past this machine's noise (18 bcts_1 tiles, one thread)

SURVEY_FORMAT = 3  # what a survey's file holds: 2 keeps its farthest point picks, their radii and its sample; 3
# its positions (Tile.positions), the share it is surveyed at

if TYPE_CHECKING:  # a tile process never reads the scan: laspy and pyproj (about 0.1 s) stay out of its server's import
    from pipeline.io.scan import Piece, Scan


@dataclass(frozen=True)
class TileJob:
    """Everything a worker needs for one tile."""

    store_path: str
    result_path: str
    tile_id: int
    slices: tuple[Slice, ...]
    overlap: float
    cache_bytes: int
    budget: int
    reserve: int
    simplifier: Method  # the method with its parameters (model.methods)
    seed: int
    survey_path: str | None = None  # a stratified method's survey of this tile (its fill loss)
    detail_scale: float = 0.0       # the tile's loss level over the scan's (model.selection.FillContext)
    cover_radius: float = 0.0       # the scan-wide hole radius, scan units
    cover_count: int = 0            # the picks that cover the tile's core at that radius (its budget's floor)
    rule: ClassRule = ClassRule()   # core points it keeps whole are saved apart and never thinned
    voxels: VoxelCounts | None = None  # what the tile's survey counted (model.selection.Tile.voxels)


@dataclass(frozen=True)
class TileOutcome:
    """What a finished tile reports back: counts and time; the picks stay on disk."""

    tile_id: int
    points: int
    kept: int
    seconds: float


def bucket_piece(piece: Piece, scan: Scan, grid: DensityGrid, work_path: str, rule: ClassRule) -> BucketedPiece:
    """Read one piece once, store its rows sorted by grid cell, record it as done in the work folder;
    return its occupied cells, row starts, points kept whole per cell and points per class."""
    chunk = scan.read(piece)
    buckets = bucket_by_cell(chunk.records, chunk.xyz, piece.first, grid)
    protected_cells = grid.cell_of(chunk.xyz[rule.protected(chunk.records)])
    per_cell = np.bincount(np.searchsorted(buckets.cells, protected_cells), minlength=len(buckets.cells))
    bucketed = BucketedPiece(buckets.cells, buckets.starts, per_cell.astype(np.int64), class_histogram(chunk.records))
    work = WorkDir(Path(work_path))
    TileStore.open(work.store_path).write_piece(piece.number, buckets.rows)
    work.save_piece(piece.number, bucketed)
    return bucketed


@lru_cache(maxsize=4096)
def tile_seed(run_seed: int, tile_id: int) -> int:
    """A tile's own seed: fixed by the run seed and the tile id, whatever worker runs it (kept for the tile's
    second load: numpy's SeedSequence takes about 0.25 ms, a twelfth of loading a 31k-point tile)."""
    return int(np.random.SeedSequence([run_seed, tile_id]).generate_state(1)[0])


def simplify_tile(job: TileJob, plan: TilePlan) -> TileOutcome:
    """Pick budget+reserve core points of one tile in priority order; save their records and xyz to
    result_path, so the stitch reads only the kept points, not every tile's core and halo again; core
    points the class rule keeps whole are saved apart (`whole`) and were never candidates."""
    started = time.perf_counter()
    tile, records, whole = load_tile(job.store_path, job.slices, job.cache_bytes, plan, job.tile_id, job.overlap,
                                     job.seed, job.rule)
    context = None if job.survey_path is None else FillContext(load_fill_loss(Path(job.survey_path), tile.core),
                                                                job.detail_scale, job.cover_radius, kept=job.budget,
                                                                cover_count=job.cover_count)
    tile = replace(tile, context=context, voxels=job.voxels)
    count = min(job.budget + job.reserve, tile.core_count)
    picked = job.simplifier(tile, count) if count else Selection.of(tile, np.empty(0, np.int64))
    write_atomically(Path(job.result_path),
                     lambda tmp: save_npz(tmp, records=take_records(records, picked.indices),
                                          xyz=picked.xyz + tile.centre, whole=take_records(records, whole),
                                          whole_xyz=tile.xyz[whole] + tile.centre))
    return TileOutcome(job.tile_id, len(tile.xyz), len(picked.indices) + len(whole), time.perf_counter() - started)


def load_tile(store_path: str, slices: tuple[Slice, ...], cache_bytes: int, plan: TilePlan, tile_id: int,
              overlap: float, run_seed: int, rule: ClassRule) -> tuple[Tile, np.ndarray, np.ndarray]:
    """A tile's core and halo points, centred on the core's mean, their raw records (same order), and the
    indices of the core points `rule` keeps whole: they stay in the tile as context, outside its core."""
    store = TileStore.reader(Path(store_path))
    scales, offsets = stored_scaling(store)
    kept_xyz: list[np.ndarray] = []
    kept_core: list[np.ndarray] = []
    own_cells_only = overlap == 0 and plan.tiles[tile_id].sub is None  # slices of its own cells: every row core

    def seen(points: StoredPoints) -> np.ndarray:
        """Core and halo of a batch of rows; their coordinates and core mask are kept too, in the order the
        store joins the kept rows, so neither is computed twice."""
        xyz = grid_xyz(points.records, scales, offsets)
        if own_cells_only:  # no cell lookups (bcts fps: its simplify phase a few % faster)
            kept_xyz.append(xyz)
            kept_core.append(np.ones(len(xyz), dtype=bool))
            return kept_core[-1]
        core = plan.core_mask(tile_id, xyz)
        keep = plan.halo_mask(core, tile_id, xyz, overlap)
        every = keep.all()  # a method that reads no halo keeps every row it loads: no copies then
        kept_xyz.append(xyz if every else xyz[keep])
        kept_core.append(core if every else core[keep])
        return keep

    records = store.load(slices, cache_bytes, keep=seen).records  # a crowded neighbour is never held whole
    xyz = np.concatenate(kept_xyz) if kept_xyz else np.empty((0, 3))
    core = np.concatenate(kept_core) if kept_core else np.empty(0, dtype=bool)
    if len(xyz) != len(records):
        raise AssertionError(f"tile {tile_id}: {len(records)} rows kept but {len(xyz)} coordinates")
    if own_cells_only and len(records) != plan.tiles[tile_id].count:  # slices that reached past its cells
        raise AssertionError(f"tile {tile_id}: {len(records)} rows in its own cells' slices, "
                             f"{plan.tiles[tile_id].count} planned")
    protected = core & rule.protected(records)
    core &= ~protected
    owned = core | protected
    centre = column_mean(xyz if owned.all() else xyz[owned]) if owned.any() else np.zeros(3)
    return Tile(xyz - centre, core, centre, tile_seed(run_seed, tile_id)), records, np.flatnonzero(protected)


def stored_scaling(store: TileStore) -> tuple[np.ndarray, np.ndarray]:
    """The (3,) scales and offsets that turn the store's records into coordinates."""
    attrs = store.attrs
    return np.asarray(attrs["scales"]), np.asarray(attrs["offsets"])


def sort_crowded(slices: tuple[Slice, ...], store_path: str, grid: DensityGrid, crowded: np.ndarray,
                 rule: ClassRule, cache_bytes: int) -> SubCellIndex:
    """Copy one piece's rows in the crowded cells (`slices`, all of one piece) into the store sorted by
    sub-cell, so the tiles that split those cells read only their own sub-cells; return where the copy
    holds each sub-cell and the points per sub-cell `rule` keeps whole. Holds at most the piece's rows."""
    store = TileStore.open(Path(store_path))
    scales, offsets = stored_scaling(store)
    stored = store.load(slices, cache_bytes)
    rows, index = bucket_by_sub_cell(stored.records, stored.index, grid_xyz(stored.records, scales, offsets),
                                     rule.protected(stored.records), grid, crowded)
    store.write_piece(slices[0].piece, rows, crowded=True)
    return index


@dataclass(frozen=True)
class SurveyJob:
    """One tile to survey before budgets are set: its occupied voxels at each of `sizes` (scan units),
    and for a stratified method its fill loss (saved to survey_path), pick spacing and cover counts."""

    store_path: str
    survey_path: str
    tile_id: int
    slices: tuple[Slice, ...]
    overlap: float
    cache_bytes: int
    sizes: tuple[float, ...]
    simplifier: Method
    ratio: float
    seed: int
    rule: ClassRule = ClassRule()


@dataclass(frozen=True)
class TileSurvey:
    """What a tile tells the run: occupied voxels (levels,), its core count and positions (Tile.positions: the
    core but for exact twins, whose share `picks` is), mean absolute fill loss, the relative loss summed over
    the positions, (quantiles,) spacings of a trial fill's picks, of `picks`, the
    voxels (levels,) those picks occupy, on the core's grids (zeros for a method with no fill), the
    picks that cover the core at each radius of tiling.budgets.radius_grid(sizes) (-1: more than were sampled;
    empty for a method with no fill) and (quantiles,) distances from a sample of core points to the trial
    fill's nearest pick (model.chamfer_bound; empty without a fill). The sample and the farthest point picks
    stay in the survey's file, for the run's reference and floors (pipeline.engine.covers)."""

    occupied: np.ndarray
    core_count: int
    positions: int
    level: float
    loss_sum: float
    spacings: np.ndarray
    picks: int
    filled: np.ndarray
    covers: np.ndarray
    gaps: np.ndarray


@dataclass(frozen=True)
class FillSurvey:
    """A stratified method's measures of one tile's trial fill (TileSurvey's fields of the same names), and
    what its survey's file keeps for the run's reference and floors: the farthest point picks of the core,
    (picks, 3) in their order, the radius the picks before each leave covered, (picks,), and the core's sample,
    (s, 3) (model.chamfer_bound.core_sample)."""

    loss: FillLoss
    spacings: np.ndarray
    filled: np.ndarray
    covers: np.ndarray
    gaps: np.ndarray
    even_xyz: np.ndarray
    even_radii: np.ndarray
    sample_xyz: np.ndarray

    @classmethod
    def empty(cls, levels: int, covers: np.ndarray) -> "FillSurvey":
        """Nothing measured: a method with no fill (`covers` empty) or a tile whose share of the count is 0."""
        return cls(FillLoss(None, 0.0), np.empty(0), np.zeros(levels, dtype=np.int64), covers, np.empty(0),
                   np.empty((0, 3)), np.empty(0), np.empty((0, 3)))


def survey_tile(job: SurveyJob, plan: TilePlan) -> TileSurvey:
    """Measure one tile at the scan's ratio and keep the measurement in the work folder (a resumed run reads it)."""
    tile, _, _ = load_tile(job.store_path, job.slices, job.cache_bytes, plan, job.tile_id, job.overlap, job.seed,
                           job.rule)
    core_xyz, sizes = tile.xyz if tile.core.all() else tile.xyz[tile.core], np.asarray(job.sizes)
    occupied = occupied_voxels(core_xyz, sizes)
    budget = kept_count(job.ratio, tile.positions)
    fill = (survey_fill(tile, core_xyz, budget, sizes, job.simplifier) if isinstance(job.simplifier, Fill)
            else FillSurvey.empty(len(sizes), np.empty(0, dtype=np.int64)))
    core_loss = None if fill.loss.relative is None else fill.loss.relative[tile.core]
    positions_loss = core_loss if core_loss is None or tile.fill_mask is None else core_loss[tile.fill_mask[tile.core]]
    loss_sum = float(positions_loss.sum()) if positions_loss is not None else 0.0
    survey = TileSurvey(occupied, tile.core_count, tile.positions, fill.loss.level, loss_sum, fill.spacings, budget,
                        fill.filled, fill.covers, fill.gaps)
    arrays = {} if core_loss is None else {"relative": core_loss.astype(np.float32)}
    write_atomically(Path(job.survey_path), lambda tmp: save_npz(
        tmp, occupied=occupied, core_count=survey.core_count, positions=survey.positions, level=survey.level,
        loss_sum=loss_sum,
        spacings=fill.spacings, picks=budget, filled=fill.filled, covers=fill.covers, gaps=fill.gaps,
        even_xyz=fill.even_xyz, even_radii=fill.even_radii, sample_xyz=fill.sample_xyz, survey_format=SURVEY_FORMAT,
        **arrays))
    return survey


def survey_fill(tile: Tile, core_xyz: np.ndarray, budget: int, sizes: np.ndarray, simplifier: Fill) -> FillSurvey:
    """A stratified method's trial fill of `budget` core points and what the run needs from it: its loss,
    spacings and voxels, surveyed_picks farthest point picks and their cover counts, a sample of the core
    (core_xyz: (c, 3)) and the fill's distances from it."""
    if budget == 0:
        return FillSurvey.empty(len(sizes), cover_counts(core_xyz, 0, radius_grid(sizes)))
    even, shrinking = sampled_cover(core_xyz, surveyed_picks(budget, len(core_xyz)))
    covers = counts_within(shrinking, radius_grid(sizes), complete=len(even) == len(core_xyz))
    loss = simplifier.fill_loss(tile, budget)
    picks = tile.xyz[trial_fill(tile, budget, loss)]
    sample = core_sample(core_xyz)
    return FillSurvey(loss, pick_spacings(picks), occupied_voxels(picks, sizes, origin=column_min(core_xyz)), covers,
                      fill_gaps(sample, picks), core_xyz[even], shrinking, sample)


def surveyed_picks(share: int, points: int) -> int:
    """How many farthest point picks a survey samples of a tile's `points` core points, given its `share` of the
    count: SURVEY_PICKS x the share, so that most tiles' picks reach the run's reference radius
    (pipeline.engine.covers.fps_reference), about the radius of their share's picks, without a count of their own."""
    return min(points, int(np.ceil(SURVEY_PICKS * share)))


@dataclass(frozen=True)
class CoverJob:
    """A tile whose survey's picks (surveyed_picks) fell short of covering its core at a radius the
    run needs (`finest`): how many it needs at each of `radii`, and where its picks and sample are kept for
    the run's reference (None: not kept)."""

    store_path: str
    tile_id: int
    slices: tuple[Slice, ...]
    cache_bytes: int
    sample: int  # picks sampled first (covers.first_sample), more as the gap they leave asks
    radii: tuple[float, ...]
    finest: float
    seed: int
    rule: ClassRule = ClassRule()
    keep_path: str | None = None


def count_cover(job: CoverJob, plan: TilePlan) -> np.ndarray:
    """(radii,) the farthest-point picks that bring every core point of the tile within each radius (-1 below
    `finest`, where they may not), from the point the survey and the tile's own farthest point sampling start
    at (its core is loaded alone: the same points, in the same order, as its survey's sample)."""
    tile, _, _ = load_tile(job.store_path, job.slices, job.cache_bytes, plan, job.tile_id, 0.0, job.seed, job.rule)
    core_xyz = tile.xyz if tile.core.all() else tile.xyz[tile.core]
    picks, shrinking = (sampled_cover(core_xyz, job.sample, job.finest) if len(core_xyz)
                        else (np.empty(0, dtype=np.int64), np.empty(0)))
    if job.keep_path is not None:
        write_atomically(Path(job.keep_path), lambda tmp: save_npz(
            tmp, even_xyz=core_xyz[picks], even_radii=shrinking, sample_xyz=core_sample(core_xyz)))
    return counts_within(shrinking, np.array(job.radii), complete=len(picks) == len(core_xyz))


@dataclass(frozen=True)
class ReferenceJob:
    """One tile's part of the run's reference: the file holding its farthest point picks and sample (its
    survey's, or its cover count's) and how many of the picks stand for it."""

    path: str
    picks: int


@dataclass(frozen=True)
class FloorJob:
    """A tile whose kept farthest point picks (in its survey's file, or its cover count's) cover its core at the
    run's hole radius: the file, the radius and the core's points."""

    path: str
    radius: float
    points: int


def exact_floor(job: FloorJob) -> int:
    """The fewest of the tile's farthest point picks that leave no core point farther than the radius, read
    from the radius each pick leaves covered (exact: the survey's grid counts read at the grid radius below
    took up to 9 % more)."""
    with np.load(job.path) as saved:
        shrinking = saved["even_radii"]
    return int(counts_within(shrinking, np.array([job.radius]), complete=len(shrinking) == job.points)[0])


def reference_square(job: ReferenceJob) -> float:
    """The mean squared distance from the tile's sample to the first `picks` of its farthest point picks."""
    with np.load(job.path) as saved:
        even_xyz, sample_xyz = saved["even_xyz"], saved["sample_xyz"]
    if not 0 < job.picks <= len(even_xyz):
        raise ValueError(f"{job.path}: {job.picks} picks asked of the {len(even_xyz)} kept")
    return mean_square_distance(sample_xyz, even_xyz[:job.picks])


def load_survey(path: Path) -> TileSurvey | None:
    """A finished survey's summary (the per-point loss stays on disk), or None where the file is of another
    SURVEY_FORMAT (an attempt of older code with the same version: the tile is surveyed again)."""
    with np.load(path) as saved:
        if "survey_format" not in saved.files or int(saved["survey_format"]) != SURVEY_FORMAT:
            return None
        return TileSurvey(saved["occupied"], int(saved["core_count"]), int(saved["positions"]), float(saved["level"]),
                          float(saved["loss_sum"]), saved["spacings"], int(saved["picks"]), saved["filled"],
                          saved["covers"], saved["gaps"])


def load_fill_loss(path: Path, core: np.ndarray) -> FillLoss:
    """A survey's fill loss for the simplify step, on a load of the tile whose (n,) core mask is `core`: the
    survey saves it for the core (its halo has none), in the core's order, whatever halo either load holds
    (relative None when the method weighs points equally)."""
    with np.load(path) as saved:
        if "relative" not in saved.files:
            return FillLoss(None, float(saved["level"]))
        relative = np.zeros(len(core))
        relative[core] = saved["relative"]
        return FillLoss(relative, float(saved["level"]))
