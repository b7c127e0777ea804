"""`pipeline run`: read -> plan -> bucket -> simplify tiles on Dask -> stitch -> write, in bounded memory."""
from __future__ import annotations

import time
from concurrent.futures import Executor
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Sequence

import numpy as np

from model.methods import Fill
from model.rules import kept_count
from pipeline.config import RunConfig
from pipeline.engine.classes import ClassRule
from pipeline.engine.execute import cluster, map_tasks
from pipeline.engine.phases import (RESERVE_SHARE, ScanFill, bucket_scan, core_points, crowded_cells_note, make_jobs,
                                    scan_budgets, stitch_outputs)
from pipeline.engine.preflight import check_room, check_run
from pipeline.engine.processes import importing_parents_script, use_tile_processes
from pipeline.engine.stop_guard import StopGuard
from pipeline.engine.tasks import simplify_tile
from pipeline.engine.threads import local_workers, runs_in_process
from pipeline.engine.workdir import WorkDir, output_settings
from pipeline.errors import Interrupted, PipelineError, signal_exit_code
from pipeline.io.atomic import remove_stale_temporaries
from pipeline.io.copc_output import COPC_SPILL_COPIES, copc_point_format
from pipeline.io.crs import crs_label, length_unit, unit_note
from pipeline.io.output_guard import check_output
from pipeline.io.scan import Scan
from pipeline.io.writers import COPC_SUFFIX, OUTPUT_KINDS, output_kind
from pipeline.progress import Progress
from tiling.store import TileStore

if TYPE_CHECKING:
    from dask.distributed import Client


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
    hole_radius_m: tuple[float, float] | None = None  # a stratified method's hole radius and the radius before the
                                                      # Chamfer bound narrowed it, metres (None for other methods)
    floor_tiles: int = 0  # a stratified method's tiles at their cover floor, picked by farthest point sampling alone

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

    def hole_line(self) -> str | None:
        """What `pipeline run -v` says of a stratified method's hole radius (None for other methods)."""
        if self.hole_radius_m is None:
            return None
        radius, unbounded = self.hole_radius_m
        narrowed = f" (narrowed from {unbounded:.4g} m by the Chamfer bound)" if radius < unbounded else ""
        floors = (f"; {self.floor_tiles} of {self.tiles} tiles at their cover floor, picked by farthest point "
                  "sampling alone" if self.floor_tiles else "")
        return f"hole radius: {radius:.4g} m{narrowed}{floors}"


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
    most `in_process_points` points (pipeline.engine.threads.runs_in_process: the same tasks on `workers`
    threads, where starting a cluster costs more than it saves), else on a fresh local cluster.
    Finished pieces and tiles are kept in a work folder until the output is in place, so the same
    command re-run after a crash or a kill resumes; any other failure names that folder. With
    `stop_grace_s` (the CLI's), an interrupted run whose cluster has not closed within that many seconds
    ends the process (pipeline.engine.stop_guard).
    """
    if importing_parents_script():
        raise PipelineError("pipeline.run was called while a worker process imported the script that started it: "
                            "call it under `if __name__ == \"__main__\":`")
    clock = PhaseClock()
    config = config.validated()
    if scheduler is not None or client is not None:  # workers elsewhere, started in other folders: whole paths
        inputs, scratch = [Path(p).absolute() for p in inputs], Path(scratch).absolute() if scratch else None
        output = Path(output).absolute() if output is not None else None
    scan = Scan(inputs)
    output = Path(output) if output is not None else default_output(scan.paths[0])
    outputs = written_paths(output, config.levels)
    kept = kept_count(config.ratio, scan.point_count)
    for path in outputs:
        check_output(path, [Path(p) for p in inputs], overwrite, OUTPUT_KINDS)
        if output_kind(path) == COPC_SUFFIX:  # refused now, not after the whole simplification
            try:
                records = copc_point_format(scan.point_format).size * kept
            except PipelineError as exc:
                raise PipelineError(f"{path}: {exc}") from None
            check_room(path.parent, COPC_SPILL_COPIES * records, "the COPC writer's spill of the kept points",
                       "write .laz, or free space beside the output")
    unit = length_unit(scan.header)
    settings = output_settings(config)  # what the output records: lengths in metres, as given
    config = config.in_unit(unit.metres)
    work = WorkDir.of_run(output, Path(scratch) if scratch else None, scan.paths, config)
    check_run(scan, config.allow_geographic, Path(scratch or output.parent),
              kept=int(kept * (1 + RESERVE_SHARE)),
              surveyed=isinstance(config.simplifier, Fill), progress=progress or Progress(),
              held=work.held_bytes())  # an earlier attempt's work needs no room again
    if note is not None and (said := unit_note(unit, crs_label(scan.header))):
        note(said)
    if kept == 0:
        raise PipelineError(f"{scan.paths[0]}: --ratio {config.ratio} keeps 0 of {scan.point_count} points")
    for path in outputs:
        remove_stale_temporaries(path)
    work.create(output, scan.paths, config)
    tell = note or (lambda line: None)
    with work.held():  # a second run of the same command is refused before it touches the folder
        if dropped := work.drop_damaged():
            tell(f"{work.path}: {len(dropped)} unreadable file(s) of an earlier attempt made again "
                 f"({', '.join(dropped[:3])}{', ...' if len(dropped) > 3 else ''})")
        written = None
        guard = StopGuard(stop_grace_s)
        try:
            threads = local_workers(config.workers)
            elsewhere = use_tile_processes(scan.point_count, threads, config.simplifier.tile_processes_from)
            here = runs_in_process(scan.point_count, config.in_process_points, threads, config.simplifier.light_on_gil,
                                   elsewhere)
            with nullcontext(client) if client else cluster(config.workers, config.memory_limit, scheduler, here,
                                                            elsewhere) as active:
                try:
                    written, tiles, resumed, kept_whole, fill = simplify_scan(
                        scan, outputs, config, settings, work, active, clock, progress or Progress(),
                        tell)
                except KeyboardInterrupt as exc:  # the cluster closes next: bounded, if a grace is given
                    guard.arm(f"pipeline: {interrupted_line(work)}", signal_exit_code(exc))
                    raise
        except PipelineError as exc:
            if not work.has_results():
                work.remove()
                raise
            raise PipelineError(f"{exc} (finished work kept in {work.path}: re-run the same command to "
                                "resume)") from exc
        except KeyboardInterrupt as exc:  # Ctrl-C, or SIGTERM through the CLI's handler; the cluster is closed by now
            guard.cancel()
            raise interrupted(exc, work, output if written is not None else None) from None
        work.remove()
        if removed := work.remove_others(output):
            tell(f"removed {len(removed)} work folder(s) of earlier attempts at {output} with other inputs or "
                 "settings, which no run can resume")
    hole = None if fill is None else (fill.cover_radius * unit.metres, fill.unbounded_radius * unit.metres)
    return RunReport(outputs[0], scan.point_count, written[0], tiles, resumed, clock.total, clock.laps,
                     tuple(zip(outputs, written)), kept_whole, hole, 0 if fill is None else fill.floor_tiles)


def written_paths(output: Path, levels: Sequence[float]) -> list[Path]:
    """The files a run writes: `output`, or one per level with `--levels` (finest first)."""
    return [level_output(output, level) for level in levels] or [output]


def level_output(output: Path, ratio: float) -> Path:
    """Where `--levels` writes one level: `name.r0.1.laz` beside `name.laz` (`name.r0.1.copc.laz`, ...)."""
    name, kind = output.name, output_kind(output)
    if kind is None:
        return output.with_name(f"{name}.r{ratio:g}")
    return output.with_name(f"{name[:-len(kind)]}.r{ratio:g}{name[-len(kind):]}")


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
                  note: Callable[[str], None]) -> tuple[list[int], int, int, int, ScanFill | None]:
    """Bucket, plan, simplify every tile on the cluster, stitch and write each level; return points written
    per output, tiles, tiles found finished by an earlier attempt, points kept whole and a stratified
    method's scan-wide fill settings (None for other methods)."""
    clock.lap("start cluster")
    if not TileStore.exists(work.store_path):  # a resumed run keeps the pieces it stored
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
    budgets, fill, voxels = scan_budgets(client, plan, slices, counts, work, config, progress)
    jobs = make_jobs(work, plan, slices, budgets, whole, config, fill, voxels)
    pending = [job for job in jobs if not Path(job.result_path).is_file()]
    map_tasks(client, simplify_tile, pending, plan, desc="simplify", progress=progress,
              weight=lambda outcome: outcome.points, cost=core_points(plan))
    clock.lap("simplify tiles")
    results = {job.tile_id: job.result_path for job in jobs}
    written = stitch_outputs(scan, outputs, plan, results, budgets, int(counts.sum()), int(whole.sum()), config,
                             settings, progress)
    clock.lap("stitch and write")
    return written, len(jobs), len(jobs) - len(pending), int(whole.sum()), fill


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
