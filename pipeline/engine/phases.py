"""The phases of a run between reading and writing, each a call the runner makes: bucket the scan and plan
its tiles, survey them, set their budgets, make their jobs, and stitch the finished tiles into outputs."""
from __future__ import annotations

import math
from concurrent.futures import Executor
from contextlib import ExitStack
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from model.chamfer_bound import bounded_radius, estimated_chamfer
from model.methods import Fill
from model.rules import kept_count
from model.selection import VoxelCounts
from model.stratified import at_cover_floor
from pipeline.config import RunConfig, parse_size
from pipeline.engine.classes import ClassRule
from pipeline.engine.execute import map_tasks
from pipeline.engine.covers import cover_floors, fps_reference, surveyed_least
from pipeline.engine.tasks import (CoverJob, SurveyJob, TileJob, TileSurvey, bucket_piece, load_survey, sort_crowded,
                                   survey_tile)
from pipeline.engine.workdir import BucketedPiece, WorkDir
from pipeline.errors import PipelineError
from pipeline.io.crs import crs_wkt
from pipeline.io.output_meta import OutputMeta
from pipeline.io.scan import Piece, Scan
from pipeline.io.writers import write_output
from pipeline.progress import Progress, counted
from pipeline.version import __version__
from tiling.assemble import level_parts, seam_rejections
from tiling.bucket import SubCellIndex, cell_boxes, halo_slices, row_ranges
from tiling.budgets import (count_between, coverage_weights, even_spacing, feasible_radius, grouped_budgets, hole_voxels,
                            nested_budgets, pooled_quantile, radius_grid, saliency_weights)
from tiling.plan import CELLS_PER_TILE, SUB_CELLS, DensityGrid, TilePlan, crowded_cells, plan_tiles, summed_cells
from tiling.store import Slice

if TYPE_CHECKING:
    from dask.distributed import Client

RESERVE_SHARE = 0.05               # extra picks per tile, in priority order, for the seam top-up
RESERVE_MIN = 16


def bucket_scan(client: Client | Executor, scan: Scan, pieces: list[Piece], work: WorkDir, config: RunConfig, rule: ClassRule,
                progress: Progress) -> tuple[TilePlan, TileSlices, np.ndarray, np.ndarray]:
    """The one streamed pass: pieces stored sorted by grid cell (those an earlier attempt finished are
    reused); then the plan from the summed density, each tile's core+halo (and core alone) as row slices of
    the pieces, the (tiles,) core points `rule` keeps whole and the scan's (256,) points per class."""
    mins, maxs = scan.bounds
    try:
        grid = DensityGrid.covering(mins, maxs, config.tile_size)
    except ValueError as exc:
        raise PipelineError(f"{scan.paths[0]}: {exc}: pass a larger --tile-size") from None
    finished = {piece.number: work.finished_piece(piece.number) for piece in pieces}
    pending = [piece for piece in pieces if finished[piece.number] is None]
    fresh = map_tasks(client, bucket_piece, pending, scan, grid, str(work.path), rule, desc="read and bucket",
                      progress=progress, weight=lambda result: int(result.starts[-1]))
    finished.update({piece.number: result for piece, result in zip(pending, fresh)})
    buckets = [finished[piece.number] for piece in pieces]
    cells, counts = summed_cells([b.cells for b in buckets], [np.diff(b.starts) for b in buckets])
    _, protected = summed_cells([b.cells for b in buckets], [b.protected for b in buckets])
    crowded = crowded_cells(cells, counts, config.max_tile_points)
    copies = sort_crowded_cells(client, crowded, pieces, buckets, grid, work, config, rule, progress)
    sub_counts = sum(c.counts for c in copies.values()) if copies else None
    plan = plan_tiles(grid, cells, counts, config.max_tile_points, sub_counts, config.merge_limit)
    whole = plan.per_tile(protected, sum(c.protected for c in copies.values()) if copies else None)  # plan.cells == cells
    boxes = cell_boxes([b.cells for b in buckets], grid.shape[1])
    overlap = seen_overlap(config)
    seen = tile_slices(plan, overlap, pieces, buckets, copies, boxes)
    core = seen if overlap == 0 else tile_slices(plan, 0.0, pieces, buckets, copies, boxes)
    return plan, TileSlices(seen, core), whole, np.sum([b.classes for b in buckets], axis=0)


@dataclass(frozen=True)
class TileSlices:
    """Each tile's rows as slices of the stored pieces: with the halo a method reads (`seen`), and its core
    alone (`core`: a cover count's load, and a surveyed fill's picks, which need no halo). A whole-cell tile's
    core slices hold exactly its rows, which its loads take as core without looking them up (tasks.load_tile)."""

    seen: list[list[Slice]]
    core: list[list[Slice]]


def tile_slices(plan: TilePlan, overlap: float, pieces: list[Piece], buckets: list[BucketedPiece],
                copies: dict[int, SubCellIndex], boxes: np.ndarray) -> list[list[Slice]]:
    """Each tile's core and `overlap` of halo as slices of the pieces (only of the pieces its halo meets,
    not every piece for every tile; boxes: (pieces, 4) each piece's occupied cell rows and columns)."""
    slices: list[list[Slice]] = []
    for tile_id in range(len(plan.tiles)):
        i0, i1, j0, j1 = plan.halo_cell_rect(tile_id, overlap)
        meets = np.flatnonzero((boxes[:, 0] < i1) & (boxes[:, 1] > i0) & (boxes[:, 2] < j1) & (boxes[:, 3] > j0))
        slices.append([s for k in meets for s in halo_slices(plan, tile_id, overlap, pieces[k].number,
                                                             buckets[k].cells, buckets[k].starts,
                                                             copies.get(pieces[k].number))])
    return slices


def sort_crowded_cells(client: Client | Executor, crowded: np.ndarray, pieces: list[Piece],
                       buckets: list[BucketedPiece], grid: DensityGrid, work: WorkDir, config: RunConfig,
                       rule: ClassRule, progress: Progress) -> dict[int, SubCellIndex]:
    """Each piece's rows in the cells over the tile limit, copied sorted by sub-cell (one task per piece
    holding any): the sub-cell starts of each copy by piece number, from which the plan splits those
    cells and their tiles read only their own sub-cells. Empty when no cell is crowded."""
    if len(crowded) == 0:
        return {}
    cell_ranges = np.column_stack([crowded, crowded + 1])
    shares = [tuple(Slice(piece.number, int(lo), int(hi)) for lo, hi in row_ranges(b.cells, b.starts, cell_ranges))
              for piece, b in zip(pieces, buckets)]
    shares = [share for share in shares if share]
    copies = map_tasks(client, sort_crowded, shares, str(work.store_path), grid, crowded, rule,
                       chunk_cache_bytes(config), desc="sort crowded cells", progress=progress)
    return {share[0].piece: copy for share, copy in zip(shares, copies)}


def crowded_cells_note(plan: TilePlan, max_points: int, tile_size_m: float) -> str | None:
    """Say so when tiles hold more than max_points: a crowded cell is split down to sub-cells (tile size /
    512) and no further, so such a tile's task needs memory for all of its points; the tile size that
    would split them, were the points spread evenly over the sub-cell (exact twins it never splits)."""
    crowded = [tile.count for tile in plan.tiles if tile.count > max_points]
    if not crowded:
        return None
    most = max(crowded)
    smaller = tile_size_m * math.sqrt(max_points / most)
    return (f"{len(crowded)} sub-cell(s) of tile size / {CELLS_PER_TILE * SUB_CELLS} hold more than --max-tile-points "
            f"({max_points:,}) points, up to {most:,}: each is one tile and its task needs memory for all of "
            f"them; a --tile-size of about {smaller:.2g} m or less would split them, unless they share one "
            f"position (a scanner's no-return spot), which no tile size splits")


COVERAGE_LEVELS = 2.0 ** np.arange(-8, 9)  # voxel sizes, relative to the 2-D spacing estimate: 2**8 either side,
# as the estimate (occupied grid cells' area) is coarse when tiles are large against the scan (a 5 km tile on a
# 20 m scene: 30x), and with 2**4 the even spacing was then held at the finest size, a cover radius 3x too wide.
# Counting the extra levels is a shift of the sorted codes each; inside 2**4 the interpolations are unchanged.


def survey_scan(client: Client | Executor, plan: TilePlan, slices: list[list[Slice]], work: WorkDir, config: RunConfig,
                target: int, progress: Progress) -> tuple[list[TileSurvey], np.ndarray]:
    """Every tile's survey (those an earlier attempt finished are read back) and the voxel sizes (levels,)
    around the spacing `target` points give the scan, at which each counted its occupied voxels."""
    cell_area = plan.grid.cell ** 2
    spacing = float(np.sqrt(sum(t.occupied for t in plan.tiles) * cell_area / max(target, 1)))
    sizes = tuple(float(s) for s in spacing * COVERAGE_LEVELS)
    overlap, cache_bytes, rule = seen_overlap(config), chunk_cache_bytes(config), ClassRule.of(config)
    jobs = [SurveyJob(str(work.store_path), str(work.survey_path(tile_id)), tile_id, tuple(slices[tile_id]),
                      overlap, cache_bytes, sizes, config.simplifier, config.ratio, config.seed, rule)
            for tile_id in range(len(plan.tiles))]
    saved = {job.tile_id: load_survey(Path(job.survey_path)) for job in jobs if Path(job.survey_path).is_file()}
    pending = [job for job in jobs if saved.get(job.tile_id) is None]
    saved.update(zip((job.tile_id for job in pending),
                     map_tasks(client, survey_tile, pending, plan, desc="survey tiles", progress=progress,
                               cost=core_points(plan))))
    return [saved[job.tile_id] for job in jobs], np.array(sizes)


@dataclass(frozen=True)
class ScanFill:
    """The scan-wide settings of a stratified method's tiles: (tiles,) detail scales, the hole radius, the
    radius before the Chamfer bound narrowed it (the same where it did not), (tiles,) the picks that cover
    each tile at it (none before they are counted) and how many tiles' budgets are just that count (their
    floor: no fill fits beside the cover, so farthest point sampling picks them alone)."""

    detail_scales: np.ndarray
    cover_radius: float
    unbounded_radius: float
    cover_counts: np.ndarray | None = None
    floor_tiles: int = 0


def scan_fill(surveys: list[TileSurvey], occupied: np.ndarray, sizes: np.ndarray, target: int, method: Fill,
              planned: Callable[[float, np.ndarray], np.ndarray], lowest: float,
              reference: float) -> tuple[np.ndarray, ScanFill]:
    """Tile weights for the budgets and the fill settings that make tiles keep points as one stratified
    pass over the whole scan would: weights 1 + strength x loss / the scan's mean loss (the method's
    loss_strength), and a hole radius of its `cover_spacings` times the scan's typical pick spacing, but not
    finer than the even spacing `target` points can cover (the default's floor before 0.3.11), then narrowed
    where its `chamfer_bound` asks (model.chamfer_bound) against the `reference` Chamfer distance (one FPS of
    the whole scan's, as pipeline.engine.covers.fps_reference measures it) for the (tiles,) budgets
    `planned(radius, weights)` gives at the default's weights (strength 1: the radius is the default's at any
    strength), down to `lowest` at most (tiling.budgets.feasible_radius: below it the floors would exceed the
    target and tiles would cut their hole cover short)."""
    counts, levels = np.array([s.positions for s in surveys]), np.array([s.level for s in surveys])  # twins weigh 0
    loss_sums = np.array([s.loss_sum for s in surveys])
    weights, scales = saliency_weights(counts, levels, loss_sums, method.loss_strength())
    spacing = pooled_quantile([s.spacings for s in surveys], np.array([s.picks for s in surveys]))
    widest = max(method.cover_spacings * spacing, even_spacing(occupied, sizes, target))
    default_weights = saliency_weights(counts, levels, loss_sums)[0]
    radius = chamfer_radius(surveys, lambda r: planned(r, default_weights), method.chamfer_bound * reference, widest,
                            min(lowest, widest))
    return weights, ScanFill(scales, radius, widest)


def chamfer_radius(surveys: list[TileSurvey], budgets_at: Callable[[float], np.ndarray], limit: float, widest: float,
                   lowest: float) -> float:
    """The widest hole radius in [lowest, widest] at which the scan's Chamfer distance, estimated from the
    tiles' surveys (model.chamfer_bound), is at most `limit`: each tile's trial fill stretched from its share
    of the count to the budget `budgets_at(radius)` ((tiles,)) gives it there."""
    measured = np.array([len(survey.gaps) > 0 for survey in surveys])
    if not measured.any():
        return widest
    gaps = np.array([survey.gaps for survey in surveys if len(survey.gaps)])
    counts = np.array([survey.core_count for survey in surveys], dtype=np.float64)[measured]
    shares = np.array([survey.picks for survey in surveys], dtype=np.float64)[measured]

    def estimate(radius: float) -> float:
        stretch = np.sqrt(shares / np.maximum(budgets_at(radius), 1e-9)[measured])
        return estimated_chamfer(gaps, stretch, counts, radius)

    return bounded_radius(estimate, limit, widest, lowest)


def scan_budgets(client: Client | Executor, plan: TilePlan, slices: TileSlices, counts: np.ndarray,
                 work: WorkDir, config: RunConfig,
                 progress: Progress) -> tuple[np.ndarray, ScanFill | None, list[VoxelCounts] | None]:
    """(tiles,) budgets for the (tiles,) points each tile thins, summing to round(ratio * their sum), the
    fill settings of a stratified method's tiles (None for other methods) and each tile's surveyed voxel
    counts (None unsurveyed): a method that spaces points evenly or follows saliency surveys every tile
    first, so tiles share out the points as one pass over the whole scan would."""
    target = kept_count(config.ratio, int(counts.sum()))
    weights, floors, holes, fill, voxels = None, np.minimum(counts, 1), None, None, None  # no tile left empty
    simplifier = config.simplifier
    if simplifier.spaces_evenly or isinstance(simplifier, Fill):
        surveys, sizes = survey_scan(client, plan, slices.seen, work, config, target, progress)
        occupied = np.array([survey.occupied for survey in surveys])
        voxels = [VoxelCounts(sizes, survey.occupied) for survey in surveys]
        if isinstance(simplifier, Fill):
            # saliency shared as one pass would: one fill rate for every tile, plus a point for each hole its
            # trial fill left, and at least the picks that cover it at the hole radius, so a sparse tile can
            # cover all its holes
            counting = (client, plan, slices.core)
            tasks = (work, config, progress, chunk_cache_bytes(config), core_points(plan))
            surveys, reference, counted = fps_reference(*counting, surveys, sizes, target, *tasks)
            least = surveyed_least(surveys)
            planned = planned_budgets(surveys, sizes, counts, config.ratio, plan.budget_groups(), least)
            weights, fill = scan_fill(surveys, occupied, sizes, target, simplifier, planned,
                                      feasible_radius(least, radius_grid(sizes), target), reference)
            holes = hole_voxels(occupied, np.array([survey.filled for survey in surveys]), sizes, fill.cover_radius)
            floors = cover_floors(*counting, surveys, sizes, fill.cover_radius, *tasks, counted)
            fill = replace(fill, cover_counts=floors)
        else:  # spaced evenly: tiles share out the points as one pass over the whole scan would
            weights = coverage_weights(occupied, sizes, target)
    budgets = grouped_budgets(counts, config.ratio, plan.budget_groups(), floors=floors, weights=weights, extra=holes)
    if fill is not None:
        fill = replace(fill, floor_tiles=int(np.count_nonzero((budgets > 0) & at_cover_floor(budgets, floors))))
    return budgets, fill, voxels


def planned_budgets(surveys: list[TileSurvey], sizes: np.ndarray, counts: np.ndarray, ratio: float,
                    groups: np.ndarray, least: np.ndarray) -> Callable[[float, np.ndarray], np.ndarray]:
    """(radius, (tiles,) weights) -> the (tiles,) budgets a stratified method's tiles would get at that hole
    radius, as scan_budgets shares them but with floors read from `least` (tiling.budgets.least_covers,
    interpolated between the survey's grid radii: tiling.budgets.count_between): what the Chamfer bound is
    estimated on."""
    occupied, filled = np.array([s.occupied for s in surveys]), np.array([s.filled for s in surveys])
    radii = radius_grid(sizes)

    def planned(radius: float, weights: np.ndarray) -> np.ndarray:
        floors = count_between(least, radii, radius).astype(np.int64)
        return grouped_budgets(counts, ratio, groups, floors=floors, weights=weights,
                               extra=hole_voxels(occupied, filled, sizes, radius))
    return planned


def make_jobs(work: WorkDir, plan: TilePlan, slices: TileSlices, budgets: np.ndarray, whole: np.ndarray,
              config: RunConfig, fill: ScanFill | None = None,
              voxels: list[VoxelCounts] | None = None) -> list[TileJob]:
    """One job per tile that keeps a point (a budget, or points kept whole), in tile order: neighbours
    share pieces, so caches stay warm."""
    jobs = []
    overlap, cache_bytes, rule = picks_overlap(config), chunk_cache_bytes(config), ClassRule.of(config)
    loads = slices.seen if overlap > 0 else slices.core
    for tile_id, tile in enumerate(plan.tiles):
        budget = int(budgets[tile_id])
        if budget == 0 and whole[tile_id] == 0:
            continue
        reserve = min(tile.count - int(whole[tile_id]) - budget, max(RESERVE_MIN, int(np.ceil(RESERVE_SHARE * budget))))
        surveyed = {} if fill is None else dict(survey_path=str(work.survey_path(tile_id)),
                                                 detail_scale=float(fill.detail_scales[tile_id]),
                                                 cover_radius=fill.cover_radius,
                                                 cover_count=0 if fill.cover_counts is None
                                                 else int(fill.cover_counts[tile_id]))
        jobs.append(TileJob(str(work.store_path), str(work.tile_path(tile_id)), tile_id, tuple(loads[tile_id]),
                            overlap, cache_bytes, budget, reserve, config.simplifier, config.seed, **surveyed,
                            rule=rule, voxels=None if voxels is None else voxels[tile_id]))
    return jobs


def stitch_outputs(scan: Scan, outputs: list[Path], plan: TilePlan, results: dict[int, str], budgets: np.ndarray,
                   thinned: int, whole: int, config: RunConfig, settings: dict[str, Any],
                   progress: Progress) -> list[int]:
    """Resolve the seams once, then write each output level from the finished tiles' `results` (tile id ->
    result file), one tile in memory at a time; the points written to each. `thinned` points were
    thinned to `budgets`, `whole` kept whole (in every level)."""
    with progress.phase("resolve seams", len(results), unit="tile") as phase:
        rejections = seam_rejections(plan, results, budgets, config.seam_tolerance, on_tile=phase.update)
    written = []
    level = budgets
    with ExitStack() as renamed:  # every level in place at once, or none
        for path, ratio in zip(outputs, config.levels or (config.ratio,)):
            # each level shared from the one before, not from the finest: a largest-remainder share is not
            # monotone in its total (0.4 gave a tile 0 points where 0.3 gave it 1), and a level must be a subset
            level = nested_budgets(level, kept_count(ratio, thinned))
            meta = OutputMeta(crs_wkt(scan.header), [str(p) for p in scan.paths], ratio, config.method,
                              __version__, settings, config.simplifier.trained_weights())
            with progress.phase(f"write {path.name}", len(results), unit="tile") as phase:
                parts = counted(level_parts(plan, results, budgets, level, rejections, scan.scales,
                                            scan.offsets), phase,
                                lambda part: len(part.records))
                written.append(write_output(path, scan.header, int(level.sum()) + whole, parts, meta, renamed))
    return written


def core_points(plan: TilePlan) -> Callable[[TileJob | SurveyJob | CoverJob], int]:
    """A tile task's expected work for map_tasks' submission order: its tile's core points."""
    return lambda job: plan.tiles[job.tile_id].count


def seen_overlap(config: RunConfig) -> float:
    """How far past its core a tile's survey (and, but for a surveyed fill's, its picks: picks_overlap) loads
    it: the halo, or nothing for a method that never looks at it (fps, voxel, random pick from the core
    alone: the same picks, without reading and holding the halo, up to 0.9x a dense tile's core on a
    mobile street)."""
    return config.overlap if config.simplifier.reads_halo else 0.0


def picks_overlap(config: RunConfig) -> float:
    """How far past its core a tile's picks load it: its seen halo, or nothing for a surveyed fill (the halo
    serves its survey's loss, which is saved for the core; the fill and hole cover pick among and measure
    the core alone), so its picks neither read nor hold the halo: lone-star's tiles load 1.92 points per
    core point with it."""
    return seen_overlap(config) if config.simplifier.picks_read_halo else 0.0


def chunk_cache_bytes(config: RunConfig) -> int:
    """Memory each process may spend caching stored row chunks (`cache_memory`, part of its memory limit)."""
    return parse_size(config.cache_memory, "cache-memory")
