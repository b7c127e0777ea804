"""`pipeline run`: read -> plan -> bucket -> simplify tiles on Dask -> stitch -> write, in bounded memory."""
from __future__ import annotations

import math
import time
from concurrent.futures import Executor
from contextlib import nullcontext
from dataclasses import dataclass
from importlib.metadata import version
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Sequence

import numpy as np

from model.registry import CORE_ONLY, EVEN_SPACING, FILL_LOSSES
from model.stratified import COVER_SPACINGS
from pipeline.config import RunConfig, parse_size
from pipeline.crs import crs_label, crs_wkt, length_unit, unit_note
from pipeline.errors import Interrupted, PipelineError, signal_exit_code
from pipeline.assemble import level_parts, seam_rejections
from pipeline.atomic import remove_stale_temporaries
from pipeline.classes import ClassRule
from pipeline.execute import cluster, map_tasks
from pipeline.output_guard import check_output
from pipeline.progress import Progress, counted
from pipeline.scan import Piece, Scan
from pipeline.stop_guard import StopGuard
from pipeline.threads import local_workers, runs_in_process
from pipeline.tasks import (SurveyJob, TileJob, TileSurvey, bucket_piece, load_survey, simplify_tile, sort_crowded,
                            survey_tile)
from pipeline.validate import check_room, check_run
from pipeline.workdir import BucketedPiece, WorkDir, output_settings
from pipeline.output_meta import OutputMeta
from pipeline.copc_output import COPC_SPILL_COPIES, copc_point_format
from pipeline.writers import COPC_SUFFIX, OUTPUT_SUFFIXES, write_output
from tiling.budgets import (coverage_weights, even_spacing, grouped_budgets, nested_budgets, pooled_median,
                            saliency_weights, target_count, voxels_at)
from tiling.bucket import SubCellIndex, cell_boxes, halo_slices, row_ranges
from tiling.plan import CELLS_PER_TILE, SUB_CELLS, DensityGrid, TilePlan, crowded_cells, plan_tiles, summed_cells
from tiling.store import Slice, TileStore

if TYPE_CHECKING:
    from dask.distributed import Client

RESERVE_SHARE = 0.05               # extra picks per tile, in priority order, for the seam top-up
RESERVE_MIN = 16


@dataclass(frozen=True)
class RunReport:
    """What a run did: where it wrote, how many points in and out, over how many tiles, how long."""

    output: Path
    input_points: int
    output_points: int
    tiles: int
    resumed_tiles: int
    seconds: float
    phases: dict[str, float]
    levels: tuple[tuple[Path, int], ...] = ()  # every output written and its points, finest first
    kept_whole: int = 0  # points a class rule kept whole (counted in output_points)

    def summary(self, config: RunConfig) -> str:
        """What `pipeline run` prints: a line per output written, and what a class rule kept whole."""
        rate = self.input_points / max(self.seconds, 1e-9)
        resumed = f", {self.resumed_tiles} finished earlier" if self.resumed_tiles else ""
        lines = [f"{path}: {points:,} of {self.input_points:,} points" for path, points in self.levels]
        lines[0] += f" ({self.tiles} tiles{resumed}, {self.seconds:.1f} s, {rate:,.0f} points/s)"
        rule = ClassRule.of(config)
        if rule.active:
            thinned = self.input_points - self.kept_whole
            lines.append(f"{rule.describe()}: {self.kept_whole:,} points kept whole; the other {thinned:,} thinned to "
                         + ", ".join(f"{points - self.kept_whole:,}" for _, points in self.levels))
        return "\n".join(lines)


def default_output(first_input: Path) -> Path:
    """`<stem>.simplified.<las|laz>` in the current directory (inputs may sit on read-only storage)."""
    stem = first_input.name
    for suffix in (".copc.laz", ".laz", ".las", ".ply"):
        if stem.lower().endswith(suffix):
            stem = stem[: -len(suffix)]
            break
    suffix = ".las" if first_input.suffix.lower() == ".las" else ".laz"
    return Path.cwd() / f"{stem}.simplified{suffix}"


def run_scan(inputs: Sequence[str | Path], output: str | Path | None, config: RunConfig, overwrite: bool = False,
             scratch: str | Path | None = None, progress: Progress | None = None, scheduler: str | None = None,
             client: Client | None = None, note: Callable[[str], None] | None = None,
             stop_grace_s: float | None = None) -> RunReport:
    """Simplify one scan (one or more files) to `output`; the Python twin of `pipeline run`.

    Lengths in `config` are metres, converted to the scan's horizontal unit (its CRS's: foot, US survey
    foot, ...); `note` hears that once, or that metres were assumed for lack of a CRS.
    Runs on `client` if given, else on the cluster at `scheduler`, else in this process for a scan of at
    most `in_process_points` points (the same tasks on `workers` threads: starting a cluster costs more
    than it saves), else on a fresh local cluster.
    Finished pieces and tiles are kept in a work folder until the output is in place, so the same
    command re-run after a crash or a kill resumes; any other failure names that folder. With
    `stop_grace_s` (the CLI's), an interrupted run whose cluster has not closed within that many seconds
    ends the process (pipeline.stop_guard).
    """
    clock = PhaseClock()
    config = config.validated()
    scan = Scan(inputs)
    output = Path(output) if output is not None else default_output(scan.paths[0])
    outputs = written_paths(output, config.levels)
    kept = target_count(config.ratio, scan.point_count)
    for path in outputs:
        check_output(path, [Path(p) for p in inputs], overwrite, OUTPUT_SUFFIXES)
        if path.name.lower().endswith(COPC_SUFFIX):  # refused now, not after the whole simplification
            try:
                records = copc_point_format(scan.point_format).size * kept
            except PipelineError as exc:
                raise PipelineError(f"{path}: {exc}") from None
            check_room(path.parent, COPC_SPILL_COPIES * records, "the COPC writer's spill of the kept points",
                       "write .laz, or free space beside the output")
    check_run(scan, config.allow_geographic, Path(scratch or output.parent),
              kept=int(kept * (1 + RESERVE_SHARE)),
              surveyed=config.method in FILL_LOSSES, progress=progress or Progress())
    unit = length_unit(scan.header)
    settings = output_settings(config)  # what the output records: lengths in metres, as given
    config = config.in_unit(unit.metres)
    if note is not None and (said := unit_note(unit, crs_label(scan.header))):
        note(said)
    if target_count(config.ratio, scan.point_count) == 0:
        raise PipelineError(f"{scan.paths[0]}: --ratio {config.ratio} keeps 0 of {scan.point_count} points")
    for path in outputs:
        remove_stale_temporaries(path)
    work = WorkDir.for_run(output, Path(scratch) if scratch else None, scan.paths, config)
    written = None
    guard = StopGuard(stop_grace_s)
    try:
        here = runs_in_process(scan.point_count, config.in_process_points, local_workers(config.workers))
        with nullcontext(client) if client else cluster(config.workers, config.memory_limit, scheduler, here) as active:
            try:
                written, tiles, resumed, kept_whole = simplify_scan(scan, outputs, config, settings, work, active, clock,
                                                                    progress or Progress(), note or (lambda line: None))
            except KeyboardInterrupt as exc:  # the cluster closes next: bounded, if a grace is given
                guard.arm(f"pipeline: {interrupted_line(work)}", signal_exit_code(exc))
                raise
    except PipelineError as exc:
        if not work.has_results():
            work.remove()
            raise
        raise PipelineError(f"{exc} (finished work kept in {work.path}: re-run the same command to resume)") from exc
    except KeyboardInterrupt as exc:  # Ctrl-C, or SIGTERM through the CLI's handler; the cluster is closed by now
        guard.cancel()
        raise interrupted(exc, work, output if written is not None else None) from None
    work.remove()
    return RunReport(outputs[0], scan.point_count, written[0], tiles, resumed, clock.total, clock.laps,
                     tuple(zip(outputs, written)), kept_whole)


def written_paths(output: Path, levels: Sequence[float]) -> list[Path]:
    """The files a run writes: `output`, or one per level with `--levels` (finest first)."""
    return [level_output(output, level) for level in levels] or [output]


def level_output(output: Path, ratio: float) -> Path:
    """Where `--levels` writes one level: `name.r0.1.laz` beside `name.laz` (`name.r0.1.copc.laz`, ...)."""
    name = output.name
    for suffix in (".copc.laz", *OUTPUT_SUFFIXES):
        if name.lower().endswith(suffix):
            return output.with_name(f"{name[:-len(suffix)]}.r{ratio:g}{name[-len(suffix):]}")
    return output.with_name(f"{name}.r{ratio:g}")


def interrupted(exc: KeyboardInterrupt, work: WorkDir, written: Path | None) -> Interrupted:
    """The one line for a stopped run: what is kept and how to resume (the work folder stays if it holds any)."""
    code = signal_exit_code(exc)
    if written is not None:  # stopped while the cluster closed: the output is whole
        work.remove()
        return Interrupted(f"interrupted after {written} was written in full; it is kept", code)
    if work.has_results():
        return Interrupted(interrupted_line(work), code)
    work.remove()
    return Interrupted("interrupted before any work finished; nothing was written", code)


def interrupted_line(work: WorkDir) -> str:
    """The one line for a run stopped with finished work in `work`."""
    return f"interrupted; finished work kept in {work.path}: re-run the same command to resume"


def simplify_scan(scan: Scan, outputs: list[Path], config: RunConfig, settings: dict[str, Any], work: WorkDir,
                  client: Client | Executor, clock: "PhaseClock", progress: Progress,
                  note: Callable[[str], None]) -> tuple[list[int], int, int, int]:
    """Bucket, plan, simplify every tile on the cluster, stitch and write each level; return points written
    per output, tiles, tiles found finished by an earlier attempt, and points kept whole."""
    clock.lap("start cluster")
    if not (work.store_path / "zarr.json").is_file():  # a resumed run keeps the pieces it stored
        TileStore.create(work.store_path, scan.dtype, {"scales": scan.scales.tolist(), "offsets": scan.offsets.tolist()})
    rule = ClassRule.of(config)
    plan, slices, whole, classes = bucket_scan(client, scan, scan.pieces(config.chunk_points), work, config, rule,
                                               progress)
    for code in (*rule.keep, *rule.thin):
        if classes[code] == 0:
            note(f"class {code} has no points in the scan")
    if said := crowded_cells_note(plan, config.max_tile_points, settings["tile_size"]):
        note(said)
    clock.lap("read and bucket")
    counts = np.array([t.count for t in plan.tiles], dtype=np.int64) - whole  # the points to thin
    target = target_count(config.ratio, int(counts.sum()))
    weights, floors, fill = None, np.minimum(counts, 1), None  # no tile left empty
    if config.method in EVEN_SPACING or config.method in FILL_LOSSES:
        surveys, sizes = survey_scan(client, plan, slices, work, config, target, progress)
        occupied = np.array([survey.occupied for survey in surveys])
        if config.method in EVEN_SPACING:  # tiles share out the points as one pass over the whole scan would
            weights = coverage_weights(occupied, sizes, target)
        else:  # saliency shared as one pass would; a point in every voxel of the hole radius, so every tile
            weights, fill = scan_fill(surveys, occupied, sizes, target)  # keeps enough to cover its holes
            floors = np.ceil(voxels_at(occupied, sizes, fill.cover_radius)).astype(np.int64)
    budgets = grouped_budgets(counts, config.ratio, plan.budget_groups(), floors=floors, weights=weights)
    jobs = make_jobs(work, plan, slices, budgets, whole, config, fill)
    pending = [job for job in jobs if not Path(job.result_path).is_file()]
    map_tasks(client, simplify_tile, pending, plan, desc="simplify", progress=progress,
              weight=lambda outcome: outcome.points, cost=core_points(plan))
    clock.lap("simplify tiles")
    results = {job.tile_id: job.result_path for job in jobs}
    with progress.phase("resolve seams", len(results), unit="tile") as phase:
        rejections = seam_rejections(plan, results, budgets, config.seam_tolerance, on_tile=phase.update)
    written = []
    for path, ratio in zip(outputs, config.levels or (config.ratio,)):
        level = nested_budgets(budgets, target_count(ratio, int(counts.sum())))
        meta = OutputMeta(crs_wkt(scan.header), [str(p) for p in scan.paths], ratio, config.method,
                          version("lidar-simplify"), settings)
        with progress.phase(f"write {path.name}", len(results), unit="tile") as phase:
            parts = counted(level_parts(plan, results, budgets, level, rejections, scan), phase,
                            lambda part: len(part.records))
            written.append(write_output(path, scan.header, int(level.sum() + whole.sum()), parts, meta))
    clock.lap("stitch and write")
    return written, len(jobs), len(jobs) - len(pending), int(whole.sum())


def core_points(plan: TilePlan) -> Callable[[TileJob | SurveyJob], int]:
    """A tile task's expected work for map_tasks' submission order: its tile's core points."""
    return lambda job: plan.tiles[job.tile_id].count


def crowded_cells_note(plan: TilePlan, max_points: int, tile_size_m: float) -> str | None:
    """Say so when tiles hold more than max_points: a crowded cell is split down to sub-cells (tile size /
    512) and no further, so such a tile's task needs memory for all of its points; the tile size that
    would split them, were the points spread evenly over the sub-cell."""
    crowded = [tile.count for tile in plan.tiles if tile.count > max_points]
    if not crowded:
        return None
    most = max(crowded)
    smaller = tile_size_m * math.sqrt(max_points / most)
    return (f"{len(crowded)} sub-cell(s) of tile size / {CELLS_PER_TILE * SUB_CELLS} hold more than --max-tile-points "
            f"({max_points:,}) points, up to {most:,}: each is one tile and its task needs memory for all of "
            f"them; a --tile-size of about {smaller:.2g} m or less would split them")


class PhaseClock:
    """Seconds spent in each named phase of a run, for the summary and the benchmarks."""

    def __init__(self) -> None:
        self.laps: dict[str, float] = {}
        self._first = self._last = time.perf_counter()

    @property
    def total(self) -> float:
        """Seconds since the clock started."""
        return time.perf_counter() - self._first

    def lap(self, phase: str) -> None:
        """Close the phase that just ended."""
        now = time.perf_counter()
        self.laps[phase] = now - self._last
        self._last = now


def bucket_scan(client: Client | Executor, scan: Scan, pieces: list[Piece], work: WorkDir, config: RunConfig, rule: ClassRule,
                progress: Progress) -> tuple[TilePlan, list[list[Slice]], np.ndarray, np.ndarray]:
    """The one streamed pass: pieces stored sorted by grid cell (those an earlier attempt finished are
    reused); then the plan from the summed density, each tile's core+halo as row slices of the pieces,
    the (tiles,) core points `rule` keeps whole and the scan's (256,) points per class."""
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
    plan = plan_tiles(grid, cells, counts, config.max_tile_points, sub_counts)
    whole = plan.per_tile(protected, sum(c.protected for c in copies.values()) if copies else None)  # plan.cells == cells
    boxes = cell_boxes([b.cells for b in buckets], grid.shape[1])
    slices: list[list[Slice]] = []
    for tile_id in range(len(plan.tiles)):  # only the pieces a halo meets (not every piece for every tile)
        i0, i1, j0, j1 = plan.halo_cell_rect(tile_id, seen_overlap(config))
        meets = np.flatnonzero((boxes[:, 0] < i1) & (boxes[:, 1] > i0) & (boxes[:, 2] < j1) & (boxes[:, 3] > j0))
        slices.append([s for k in meets for s in halo_slices(plan, tile_id, seen_overlap(config), pieces[k].number,
                                                             buckets[k].cells, buckets[k].starts,
                                                             copies.get(pieces[k].number))])
    return plan, slices, whole, np.sum([b.classes for b in buckets], axis=0)


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


COVERAGE_LEVELS = 2.0 ** np.arange(-4, 5)  # voxel sizes, relative to the 2-D spacing estimate


@dataclass(frozen=True)
class ScanFill:
    """The scan-wide settings of a stratified method's tiles: (tiles,) detail scales and the hole radius."""

    detail_scales: np.ndarray
    cover_radius: float


def survey_scan(client: Client | Executor, plan: TilePlan, slices: list[list[Slice]], work: WorkDir, config: RunConfig,
                target: int, progress: Progress) -> tuple[list[TileSurvey], np.ndarray]:
    """Every tile's survey (those an earlier attempt finished are read back) and the voxel sizes (levels,)
    around the spacing `target` points give the scan, at which each counted its occupied voxels."""
    cell_area = plan.grid.cell ** 2
    spacing = float(np.sqrt(sum(t.occupied for t in plan.tiles) * cell_area / max(target, 1)))
    sizes = tuple(float(s) for s in spacing * COVERAGE_LEVELS)
    jobs = [SurveyJob(str(work.store_path), str(work.survey_path(tile_id)), tile_id, tuple(slices[tile_id]),
                      seen_overlap(config), chunk_cache_bytes(config), sizes, config.method, config.ratio, config.seed,
                      ClassRule.of(config))
            for tile_id in range(len(plan.tiles))]
    pending = [job for job in jobs if not Path(job.survey_path).is_file()]
    fresh = dict(zip((job.tile_id for job in pending),
                     map_tasks(client, survey_tile, pending, plan, desc="survey tiles", progress=progress,
                               cost=core_points(plan))))
    surveys = [fresh[job.tile_id] if job.tile_id in fresh else load_survey(Path(job.survey_path)) for job in jobs]
    return surveys, np.array(sizes)


def scan_fill(surveys: list[TileSurvey], occupied: np.ndarray, sizes: np.ndarray,
              target: int) -> tuple[np.ndarray, ScanFill]:
    """Tile weights for the budgets and the fill settings that make tiles keep points as one stratified
    pass over the whole scan would: weights 1 + loss / the scan's mean loss, and a hole radius of
    COVER_SPACINGS times the scan's typical pick spacing, but never finer than the even spacing `target`
    points can cover (below it the floors would exceed the target and tiles cut their hole cover short)."""
    weights, scales = saliency_weights(np.array([s.core_count for s in surveys]), np.array([s.level for s in surveys]),
                                       np.array([s.loss_sum for s in surveys]))
    spacing = pooled_median([s.spacings for s in surveys], np.array([s.picks for s in surveys]))
    return weights, ScanFill(scales, max(COVER_SPACINGS * spacing, even_spacing(occupied, sizes, target)))


def make_jobs(work: WorkDir, plan: TilePlan, slices: list[list[Slice]], budgets: np.ndarray, whole: np.ndarray,
              config: RunConfig, fill: ScanFill | None = None) -> list[TileJob]:
    """One job per tile that keeps a point (a budget, or points kept whole), in tile order: neighbours
    share pieces, so caches stay warm."""
    jobs = []
    for tile_id, tile in enumerate(plan.tiles):
        budget = int(budgets[tile_id])
        if budget == 0 and whole[tile_id] == 0:
            continue
        reserve = min(tile.count - int(whole[tile_id]) - budget, max(RESERVE_MIN, int(np.ceil(RESERVE_SHARE * budget))))
        surveyed = {} if fill is None else dict(survey_path=str(work.survey_path(tile_id)),
                                                 detail_scale=float(fill.detail_scales[tile_id]),
                                                 cover_radius=fill.cover_radius)
        jobs.append(TileJob(str(work.store_path), str(work.tile_path(tile_id)), tile_id, tuple(slices[tile_id]),
                            seen_overlap(config), chunk_cache_bytes(config), budget, reserve, config.method,
                            config.seed, **surveyed, rule=ClassRule.of(config)))
    return jobs


def seen_overlap(config: RunConfig) -> float:
    """How far past its core a tile is loaded: the halo, or nothing for a method that never looks at it
    (fps, voxel, random pick from the core alone: the same picks, without reading and holding the halo,
    up to 0.9x a dense tile's core on a mobile street)."""
    return 0.0 if config.method in CORE_ONLY else config.overlap


def chunk_cache_bytes(config: RunConfig) -> int:
    """Memory each process may spend caching stored row chunks (`cache_memory`, part of its memory limit)."""
    return parse_size(config.cache_memory, "cache-memory")
