"""`pipeline run`: read -> plan -> bucket -> simplify tiles on Dask -> stitch -> write, in bounded memory."""
from __future__ import annotations

import time
from contextlib import nullcontext
from dataclasses import asdict, dataclass
from importlib.metadata import version
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

import numpy as np
from dask.distributed import Client

from model.registry import EVEN_SPACING, FILL_LOSSES
from model.stratified import COVER_SPACINGS
from pipeline.config import RunConfig, parse_size
from pipeline.crs import crs_label, crs_wkt, length_unit, unit_note
from pipeline.errors import Interrupted, PipelineError, signal_exit_code
from pipeline.atomic import remove_stale_temporaries
from pipeline.execute import cluster, map_tasks
from pipeline.output_guard import check_output
from pipeline.scan import Piece, Scan
from pipeline.tasks import SurveyJob, TileJob, TileSurvey, bucket_piece, load_survey, simplify_tile, survey_tile
from pipeline.validate import check_run
from pipeline.workdir import WorkDir
from pipeline.output_meta import OutputMeta, TilePart
from pipeline.writers import OUTPUT_SUFFIXES, write_output
from tiling.budgets import coverage_weights, even_spacing, pooled_median, saliency_weights, target_count, tile_budgets, voxels_at
from tiling.bucket import cell_boxes, row_ranges
from tiling.plan import DensityGrid, TilePlan, plan_tiles, summed_cells
from tiling.stitch import SeamBand, band_mask, first_accepted, resolve_seams
from tiling.store import Slice, TileStore

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
             scratch: str | Path | None = None, show_progress: bool = True, scheduler: str | None = None,
             client: Client | None = None, note: Callable[[str], None] | None = None) -> RunReport:
    """Simplify one scan (one or more files) to `output`; the Python twin of `pipeline run`.

    Lengths in `config` are metres, converted to the scan's horizontal unit (its CRS's: foot, US survey
    foot, ...); `note` hears that once, or that metres were assumed for lack of a CRS.
    Runs on `client` if given, else on the cluster at `scheduler`, else on a fresh local cluster.
    Finished pieces and tiles are kept in a work folder until the output is in place, so the same
    command re-run after a crash or a kill resumes; any other failure names that folder.
    """
    clock = PhaseClock()
    config = config.validated()
    scan = Scan(inputs)
    output = Path(output) if output is not None else default_output(scan.paths[0])
    check_output(output, [Path(p) for p in inputs], overwrite, OUTPUT_SUFFIXES)
    check_run(scan, config.allow_geographic, Path(scratch or output.parent),
              kept=int(target_count(config.ratio, scan.point_count) * (1 + RESERVE_SHARE)),
              surveyed=config.method in FILL_LOSSES)
    unit = length_unit(scan.header)
    settings = asdict(config)  # what the output records: lengths in metres, as given
    config = config.in_unit(unit.metres)
    if note is not None and (said := unit_note(unit, crs_label(scan.header))):
        note(said)
    if target_count(config.ratio, scan.point_count) == 0:
        raise PipelineError(f"{scan.paths[0]}: --ratio {config.ratio} keeps 0 of {scan.point_count} points")
    remove_stale_temporaries(output)
    work = WorkDir.for_run(output, Path(scratch) if scratch else None, scan.paths, config)
    written = None
    try:
        with nullcontext(client) if client else cluster(config.workers, config.memory_limit, scheduler) as active:
            written, tiles, resumed = simplify_scan(scan, output, config, settings, work, active, clock,
                                                       show_progress)
    except PipelineError as exc:
        if not work.has_results():
            work.remove()
            raise
        raise PipelineError(f"{exc} (finished work kept in {work.path}: re-run the same command to resume)") from exc
    except KeyboardInterrupt as exc:  # Ctrl-C, or SIGTERM through the CLI's handler; the cluster is closed by now
        raise interrupted(exc, work, output if written is not None else None) from None
    work.remove()
    return RunReport(output, scan.point_count, written, tiles, resumed, clock.total, clock.laps)


def interrupted(exc: KeyboardInterrupt, work: WorkDir, written: Path | None) -> Interrupted:
    """The one line for a stopped run: what is kept and how to resume (the work folder stays if it holds any)."""
    code = signal_exit_code(exc)
    if written is not None:  # stopped while the cluster closed: the output is whole
        work.remove()
        return Interrupted(f"interrupted after {written} was written in full; it is kept", code)
    if work.has_results():
        return Interrupted(f"interrupted; finished work kept in {work.path}: re-run the same command to resume", code)
    work.remove()
    return Interrupted("interrupted before any work finished; nothing was written", code)


def simplify_scan(scan: Scan, output: Path, config: RunConfig, settings: dict[str, Any], work: WorkDir,
                  client: Client, clock: "PhaseClock", show_progress: bool) -> tuple[int, int, int]:
    """Bucket, plan, simplify every tile on the cluster, stitch and write; return points written, tiles
    and tiles found finished by an earlier attempt."""
    clock.lap("start cluster")
    if not (work.store_path / "zarr.json").is_file():  # a resumed run keeps the pieces it stored
        TileStore.create(work.store_path, scan.dtype, {"scales": scan.scales.tolist(), "offsets": scan.offsets.tolist()})
    plan, slices = bucket_scan(client, scan, scan.pieces(config.chunk_points), work, config, show_progress)
    clock.lap("read and bucket")
    counts = np.array([t.count for t in plan.tiles], dtype=np.int64)
    target = target_count(config.ratio, int(counts.sum()))
    weights, floors, fill = None, np.minimum(counts, 1), None  # no tile left empty
    if config.method in EVEN_SPACING or config.method in FILL_LOSSES:
        surveys, sizes = survey_scan(client, plan, slices, work, config, target, show_progress)
        occupied = np.array([survey.occupied for survey in surveys])
        if config.method in EVEN_SPACING:  # tiles share out the points as one pass over the whole scan would
            weights = coverage_weights(occupied, sizes, target)
        else:  # saliency shared as one pass would; a point in every voxel of the hole radius, so every tile
            weights, fill = scan_fill(surveys, occupied, sizes, target)  # keeps enough to cover its holes
            floors = np.ceil(voxels_at(occupied, sizes, fill.cover_radius)).astype(np.int64)
    budgets = tile_budgets(counts, config.ratio, floors=floors, weights=weights)
    jobs = make_jobs(work, plan, slices, budgets, config, fill)
    pending = [job for job in jobs if not Path(job.result_path).is_file()]
    map_tasks(client, simplify_tile, pending, plan, desc="simplify", show_progress=show_progress,
              weight=lambda outcome: outcome.points)
    clock.lap("simplify tiles")
    parts = stitched_parts(plan, {job.tile_id: job for job in jobs}, budgets, config.seam_tolerance, scan)
    meta = OutputMeta(crs_wkt(scan.header), [str(p) for p in scan.paths], config.ratio, config.method,
                      version("lidar-simplify"), settings)
    written = write_output(output, scan.header, target, parts, meta)
    clock.lap("stitch and write")
    return written, len(jobs), len(jobs) - len(pending)


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


def bucket_scan(client: Client, scan: Scan, pieces: list[Piece], work: WorkDir, config: RunConfig,
                show_progress: bool) -> tuple[TilePlan, list[list[Slice]]]:
    """The one streamed pass: pieces stored sorted by grid cell (those an earlier attempt finished are
    reused); then the plan from the summed density, and each tile's core+halo as row slices of the pieces."""
    mins, maxs = scan.bounds
    try:
        grid = DensityGrid.covering(mins, maxs, config.tile_size)
    except ValueError as exc:
        raise PipelineError(f"{scan.paths[0]}: {exc}: pass a larger --tile-size") from None
    finished = {piece.number: work.finished_piece(piece.number) for piece in pieces}
    pending = [piece for piece in pieces if finished[piece.number] is None]
    fresh = map_tasks(client, bucket_piece, pending, scan, grid, str(work.path), desc="read and bucket",
                      show_progress=show_progress, weight=lambda result: int(result[1][-1]))
    finished.update({piece.number: result for piece, result in zip(pending, fresh)})
    buckets = [finished[piece.number] for piece in pieces]
    cells, counts = summed_cells([cells for cells, _ in buckets], [np.diff(starts) for _, starts in buckets])
    plan = plan_tiles(grid, cells, counts, config.max_tile_points)
    boxes = cell_boxes([cells for cells, _ in buckets], grid.shape[1])
    slices: list[list[Slice]] = []
    for tile_id in range(len(plan.tiles)):  # only the pieces a halo meets (not every piece for every tile)
        i0, i1, j0, j1 = plan.halo_cell_rect(tile_id, config.overlap)
        meets = np.flatnonzero((boxes[:, 0] < i1) & (boxes[:, 1] > i0) & (boxes[:, 2] < j1) & (boxes[:, 3] > j0))
        cell_ranges = plan.halo_cell_ranges(tile_id, config.overlap)
        slices.append([Slice(pieces[k].number, int(lo), int(hi)) for k in meets
                       for lo, hi in row_ranges(*buckets[k], cell_ranges)])
    return plan, slices


COVERAGE_LEVELS = 2.0 ** np.arange(-4, 5)  # voxel sizes, relative to the 2-D spacing estimate


@dataclass(frozen=True)
class ScanFill:
    """The scan-wide settings of a stratified method's tiles: (tiles,) detail scales and the hole radius."""

    detail_scales: np.ndarray
    cover_radius: float


def survey_scan(client: Client, plan: TilePlan, slices: list[list[Slice]], work: WorkDir, config: RunConfig,
                target: int, show_progress: bool) -> tuple[list[TileSurvey], np.ndarray]:
    """Every tile's survey (those an earlier attempt finished are read back) and the voxel sizes (levels,)
    around the spacing `target` points give the scan, at which each counted its occupied voxels."""
    cell_area = plan.grid.cell ** 2
    spacing = float(np.sqrt(sum(t.occupied for t in plan.tiles) * cell_area / max(target, 1)))
    sizes = tuple(float(s) for s in spacing * COVERAGE_LEVELS)
    jobs = [SurveyJob(str(work.store_path), str(work.survey_path(tile_id)), tile_id, tuple(slices[tile_id]),
                      config.overlap, chunk_cache_bytes(config), sizes, config.method, config.ratio, config.seed)
            for tile_id in range(len(plan.tiles))]
    pending = [job for job in jobs if not Path(job.survey_path).is_file()]
    fresh = dict(zip((job.tile_id for job in pending),
                     map_tasks(client, survey_tile, pending, plan, desc="survey tiles", show_progress=show_progress)))
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


def make_jobs(work: WorkDir, plan: TilePlan, slices: list[list[Slice]], budgets: np.ndarray,
              config: RunConfig, fill: ScanFill | None = None) -> list[TileJob]:
    """One job per tile with a non-zero budget, in tile order: neighbours share pieces, so caches stay warm."""
    jobs = []
    for tile_id, tile in enumerate(plan.tiles):
        budget = int(budgets[tile_id])
        if budget == 0:
            continue
        reserve = min(tile.count - budget, max(RESERVE_MIN, int(np.ceil(RESERVE_SHARE * budget))))
        surveyed = {} if fill is None else dict(survey_path=str(work.survey_path(tile_id)),
                                                 detail_scale=float(fill.detail_scales[tile_id]),
                                                 cover_radius=fill.cover_radius)
        jobs.append(TileJob(str(work.store_path), str(work.tile_path(tile_id)), tile_id, tuple(slices[tile_id]),
                            config.overlap, chunk_cache_bytes(config), budget, reserve, config.method, config.seed,
                            **surveyed))
    return jobs


def chunk_cache_bytes(config: RunConfig) -> int:
    """Memory each process may spend caching stored row chunks (`cache_memory`, part of its memory limit)."""
    return parse_size(config.cache_memory, "cache-memory")


def _load_result(job: TileJob) -> tuple[np.ndarray, np.ndarray]:
    """A finished tile's kept records and xyz, in priority order."""
    with np.load(job.result_path) as result:
        return result["records"], result["xyz"]


def stitched_parts(plan: TilePlan, jobs: dict[int, TileJob], budgets: np.ndarray, tolerance: float,
                   scan: Scan) -> Iterator[TilePart]:
    """Each tile's final points in tile order, after the seam pass; one tile in memory at a time."""
    bands, candidate_counts = [], np.zeros(len(plan.tiles), dtype=np.int64)
    for tile_id, job in sorted(jobs.items()):
        _, xyz = _load_result(job)
        candidate_counts[tile_id] = len(xyz)
        near = np.flatnonzero(band_mask(xyz, plan.bounds(tile_id), tolerance))
        bands.append(SeamBand(tile_id, near, xyz[near]))
    rejections = resolve_seams(bands, candidate_counts, budgets, tolerance)
    for tile_id, job in sorted(jobs.items()):
        records, xyz = _load_result(job)
        rejected = rejections.get(tile_id, np.empty(0, dtype=np.int64))
        chosen = first_accepted(len(records), int(budgets[tile_id]), rejected)
        records = _moved_to(records[chosen], xyz[chosen], scan)
        yield TilePart(tile_id, _covering(plan.bounds(tile_id), scan.decode_xyz(records)), records)


def _covering(rect: tuple[float, float, float, float], xyz: np.ndarray) -> tuple[float, float, float, float]:
    """The tile's core rectangle grown to hold its kept points: a refined point may move slightly outside."""
    if len(xyz) == 0:
        return rect
    low, high = xyz[:, :2].min(axis=0), xyz[:, :2].max(axis=0)
    return (min(rect[0], float(low[0])), min(rect[1], float(low[1])),
            max(rect[2], float(high[0])), max(rect[3], float(high[1])))


def _moved_to(records: np.ndarray, xyz: np.ndarray, scan: Scan) -> np.ndarray:
    """Records whose X/Y/Z follow xyz where a method refined the position (attributes stay the source's)."""
    moved = np.any(xyz != scan.decode_xyz(records), axis=1)
    if moved.any():
        ints = np.rint((xyz[moved] - scan.offsets) / scan.scales).astype(np.int32)
        for axis, name in enumerate("XYZ"):
            records[name][moved] = ints[:, axis]
    return records
