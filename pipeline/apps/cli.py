"""The `pipeline` command line: run, batch, info, eval, compare, report (demo and training in cli_extras).
Errors print one line and exit non-zero."""
from __future__ import annotations

import json
import logging
import os
import signal
import sys
from contextlib import contextmanager
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Iterator

import click

from pipeline.io.lean_laspy import import_laspy_lean

import_laspy_lean()  # before the imports below, which bring laspy in

import configs  # noqa: E402
from pipeline.apps.cli_extras import demo_command, train_command, train_detail_command  # noqa: E402
from pipeline.apps.defaults import COLORS, DEFAULT_SAMPLE  # noqa: E402
from pipeline.config import METHODS, build_config, load_settings, parse_list, parse_parameters  # noqa: E402
from pipeline.engine.stop_guard import STOP_GRACE_S  # noqa: E402
from pipeline.errors import (STOPS, Interrupted, PipelineError, Terminated, file_system_error,  # noqa: E402
                             signal_exit_code)
from pipeline.progress import Progress  # noqa: E402
from pipeline.version import __version__  # noqa: E402

EXIT_ERROR = 2


class OneLineErrors(click.Group):
    """Turns PipelineError (and lazrs panics) into `pipeline: error: ...` and exit code 2, no traceback;
    so too a file-system error no check foresaw (a disk filling up, a folder vanishing): it names its path.
    Ctrl-C and SIGTERM end in one line saying what was kept, exit 130 or 143."""

    def invoke(self, ctx: click.Context):
        STOPS.clear()  # a command run in-process (click's test runner, a notebook) starts with none
        arguments = list(ctx.args)  # the subcommand's, which click empties before it parses them
        previous = signal.signal(signal.SIGTERM, raise_terminated), signal.signal(signal.SIGINT, raise_interrupted)
        try:
            result = super().invoke(ctx)
            if STOPS:  # a library swallowed the stop (trimesh's optional imports catch BaseException) and work went on
                click.echo("pipeline: interrupted, but not before the command had finished: its outputs are complete",
                           err=True)
                sys.exit(signal_exit_code(STOPS[-1]))
            return result
        except (PipelineError, OSError) as exc:
            message = file_system_error(exc) if isinstance(exc, OSError) else exc
            click.echo(f"pipeline: error: {message}", err=True)
            sys.exit(EXIT_ERROR)
        except KeyboardInterrupt as exc:  # Ctrl-C or SIGTERM: one line, the shell's exit code, no traceback
            click.echo(f"pipeline: {exc if isinstance(exc, Interrupted) else 'interrupted'}", err=True)
            sys.exit(signal_exit_code(exc))
        except click.UsageError as exc:  # a bad flag or value: click says so; --log-json readers get it too
            if "--log-json" in arguments:
                log_json_line({"event": "failed", "error": exc.format_message()})
            raise
        except Exception:  # a library's error from a stop raised inside its call (see raise_stop_behind)
            if not STOPS:
                raise
            click.echo("pipeline: interrupted", err=True)
            sys.exit(signal_exit_code(STOPS[-1]))
        finally:
            signal.signal(signal.SIGTERM, previous[0])
            signal.signal(signal.SIGINT, previous[1])


def note_worker_cap(workers: int, scheduler: str | None) -> None:
    """One line on stderr when a local cluster gets fewer workers than asked for (no more than the cores)."""
    from pipeline.engine.threads import local_workers

    if scheduler is None and local_workers(workers) < workers:
        click.echo(f"pipeline: note: --workers {workers} capped at {local_workers(workers)}, the cores this "
                   "machine gives the run", err=True)


def raise_terminated(signum: int, frame: object) -> None:
    """SIGTERM unwinds the run as Ctrl-C does (the work folder kept, the cluster closed); a second one is
    ignored while that happens. Recorded in STOPS, as Ctrl-C is."""
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    STOPS.append(Terminated())
    raise STOPS[-1]


def raise_interrupted(signum: int, frame: object) -> None:
    """Ctrl-C raises KeyboardInterrupt, as Python's own handler does, and records it in STOPS."""
    STOPS.append(KeyboardInterrupt())
    raise STOPS[-1]


@click.group(cls=OneLineErrors, context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(__version__)  # this checkout's, not an installed copy's
def cli() -> None:
    """Simplify very large LiDAR scans while keeping edges, corners, poles and facades.

    \b
    Examples:
      pipeline run scan.laz --ratio 0.1 -o scan_small.laz
      pipeline run part1.laz part2.laz --ratio 0.05 -o merged.zarr --workers 4
      pipeline info scan.laz --json
      pipeline eval scan.laz scan_small.laz other.zarr
      pipeline compare scan.laz --ratios 0.2,0.1 --methods fps,learned
      pipeline demo
    """


@cli.command("run")
@click.argument("inputs", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--ratio", "-r", type=float, default=None, help="Fraction of points to keep, in (0, 1].")
@click.option("--levels", default=None, metavar="0.2,0.1,0.05",
              help="Write nested outputs NAME.r0.2.laz, NAME.r0.1.laz, ... (each a subset of the one before) from "
                   "one simplification, for overview pyramids; replaces --ratio.")
@click.option("--keep-class", default=None, metavar="6,14,15",
              help="Keep every point of these LAS classes; the ratio applies to the rest.")
@click.option("--thin-class", default=None, metavar="2",
              help="Thin only the points of these LAS classes; keep every other point.")
@click.option("--output", "-o", type=click.Path(path_type=Path), default=None,
              help="Output file: .las, .laz, .copc.laz (COPC 1.0) or .zarr. [default: ./<input>.simplified.laz, .las "
                   "for a .las input]")
@click.option("--method", "-m", type=click.Choice(METHODS), default=None, help="Simplifier. [default: learned]")
@click.option("--param", "-p", "params", multiple=True, metavar="NAME=VALUE",
              help="A parameter of the method, e.g. -m voxel -p slack=0.05 (repeatable; README: Method parameters).")
@click.option("--tile-size", type=float, default=None, help="Nominal tile edge in metres. [default: 50]")
@click.option("--overlap", type=float, default=None, help="Halo width around each tile in metres (into a split crowded cell, at most 64 of its point spacings). [default: 2]")
@click.option("--max-tile-points", type=int, default=None, help="Split tiles with more core points. [default: 200000]")
@click.option("--merge-tile-points", type=int, default=None,
              help="Merge sparse tiles (2x2 or 4x4 of them) while the merged tile holds at most this many "
                   "points (and at most --max-tile-points): fewer, larger tiles on sparse scans; 0 is off. "
                   "[default: 50000]")
@click.option("--seam-tolerance", type=float, default=None,
              help="Kept points of different tiles closer than this (m) keep one. [default: 0.01]")
@click.option("--workers", "-w", type=int, default=None, help="Dask worker processes. [default: 2]")
@click.option("--memory-limit", default=None, help="Memory limit per worker, e.g. 2GB. [default: 2GB]")
@click.option("--config", "-c", "config", default=None,
              help=f"Preset ({', '.join(configs.preset_names())}) or TOML file; flags override it. [default: default]")
@click.option("--seed", type=int, default=None, help="Seed for the random choices. [default: 0]")
@click.option("--scratch", type=click.Path(path_type=Path), default=None,
              help="Folder for temporary tiles. [default: the output's folder]")
@click.option("--scheduler", default=None, metavar="tcp://HOST:PORT",
              help="Run on this existing Dask cluster (workers need the inputs and --scratch at the same paths).")
@click.option("--overwrite", is_flag=True, help="Replace an existing output.")
@click.option("--allow-geographic", is_flag=True,
              help="Run on coordinates in degrees (EPSG:4326 etc.); sizes and distances are then in degrees.")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar or summary.")
@click.option("--verbose", "-v", is_flag=True, help="Also print the time of each phase.")
@click.option("--log-json", is_flag=True, help="Print the outcome as one JSON line on stdout (also on failure).")
@click.option("--mesh", is_flag=True, help="INPUT is a triangle mesh (.off/.obj/.ply): simplify its vertices and "
              "re-triangulate them by ball pivoting; output .ply/.obj/.off.")
def run_command(inputs: tuple[Path, ...], ratio: float | None, levels: str | None, keep_class: str | None,
                thin_class: str | None, output: Path | None, method: str | None, params: tuple[str, ...],
                tile_size: float | None, overlap: float | None, max_tile_points: int | None,
                merge_tile_points: int | None, seam_tolerance: float | None, workers: int | None,
                memory_limit: str | None, config: str | None,
                seed: int | None, scratch: Path | None, scheduler: str | None, overwrite: bool,
                allow_geographic: bool, quiet: bool, verbose: bool, log_json: bool, mesh: bool) -> None:
    """Simplify INPUTS (LAS/LAZ/COPC/PLY files that together form one scan) to one output."""
    from pipeline.engine.runner import run_scan

    with outcome_logged(log_json, input=[str(p) for p in inputs]):
        if ratio is None and levels is None and not {"ratio", "levels"} & set(load_settings(config)[0]):
            raise PipelineError("give --ratio (the fraction of points to keep) or --levels (or either in --config)")
        settings = build_config(config, ratio=ratio, method=method, method_parameters=parse_parameters(params),
                                tile_size=tile_size, overlap=overlap,
                                max_tile_points=max_tile_points, merge_tile_points=merge_tile_points,
                                seam_tolerance=seam_tolerance, workers=workers,
                                memory_limit=memory_limit, seed=seed, allow_geographic=allow_geographic or None,
                                levels=parse_list(levels, "--levels", float),
                                keep_classes=parse_list(keep_class, "--keep-class", int),
                                thin_classes=parse_list(thin_class, "--thin-class", int))
        if mesh:
            from pipeline.apps.mesh_mode import run_mesh

            unused = [flag for flag, value in (
                ("--levels", levels), ("--keep-class", keep_class), ("--thin-class", thin_class),
                ("--tile-size", tile_size), ("--overlap", overlap), ("--max-tile-points", max_tile_points),
                ("--merge-tile-points", merge_tile_points), ("--seam-tolerance", seam_tolerance),
                ("--workers", workers), ("--memory-limit", memory_limit), ("--scratch", scratch),
                ("--scheduler", scheduler), ("--allow-geographic", allow_geographic or None)) if value is not None]
            if unused:  # taken silently, they would seem to have been applied
                raise PipelineError(f"--mesh simplifies one mesh's vertices as a whole, in this process: {unused[0]} "
                                    "does not apply")
            mesh_report = run_mesh(inputs, output, settings, overwrite=overwrite)
            if not quiet:
                click.echo(mesh_report.summary())
            return
        if not quiet:
            note_worker_cap(settings.workers, scheduler)
        report = run_scan(list(inputs), output, settings, overwrite=overwrite, scratch=scratch,
                          progress=Progress.for_terminal(quiet, log_json), scheduler=scheduler, stop_grace_s=STOP_GRACE_S,
                          note=None if quiet or log_json else lambda line: click.echo(f"pipeline: note: {line}",
                                                                                      err=True))
    if log_json:
        log_json_line({"event": "done", "input": [str(p) for p in inputs], "output": str(report.output),
                       "input_points": report.input_points, "output_points": report.output_points,
                       "kept_whole": report.kept_whole,
                       "levels": [{"output": str(path), "points": points} for path, points in report.levels],
                       "tiles": report.tiles, "resumed_tiles": report.resumed_tiles,
                       "seconds": round(report.seconds, 3), "phases": report.phases,
                       "hole_radius_m": None if report.hole_radius_m is None else report.hole_radius_m[0],
                       "floor_tiles": report.floor_tiles})
    elif not quiet:
        click.echo(report.summary(settings))
    if verbose:
        click.echo("  ".join(f"{phase}: {seconds:.2f} s" for phase, seconds in report.phases.items()))
        if said := report.hole_line():
            click.echo(said)


@cli.command("batch")
@click.argument("jobs", type=click.Path(path_type=Path))
@click.option("--out-dir", type=click.Path(path_type=Path), default=None,
              help="Output folder (required for a folder of scans; overrides out_dir of a job file).")
@click.option("--ratio", "-r", type=float, default=None, help="Fraction kept, for every job (overrides the file).")
@click.option("--method", "-m", type=click.Choice(METHODS), default=None, help="Simplifier for every job.")
@click.option("--param", "-p", "params", multiple=True, metavar="NAME=VALUE", help="A method parameter for every job.")
@click.option("--config", "-c", "config", default=None, help="Preset or TOML file for every job.")
@click.option("--workers", "-w", type=int, default=None, help="Dask worker processes. [default: 2]")
@click.option("--memory-limit", default=None, help="Memory limit per worker, e.g. 2GB. [default: 2GB]")
@click.option("--scheduler", default=None, metavar="tcp://HOST:PORT", help="Run on this existing Dask cluster.")
@click.option("--scratch", type=click.Path(path_type=Path), default=None, help="Folder for temporary tiles.")
@click.option("--manifest", type=click.Path(path_type=Path), default=None,
              help="Batch manifest. [default: <out-dir>/batch-manifest.json, or <JOBS>.manifest.json]")
@click.option("--overwrite", is_flag=True, help="Replace existing outputs the batch did not write itself.")
@click.option("--log-json", is_flag=True, help="One JSON object per line on stdout, for cron and log collectors.")
def batch_command(jobs: Path, out_dir: Path | None, ratio: float | None, method: str | None, params: tuple[str, ...],
                  config: str | None, workers: int | None, memory_limit: str | None, scheduler: str | None,
                  scratch: Path | None, manifest: Path | None, overwrite: bool, log_json: bool) -> None:
    """Run many scans: JOBS is a folder (each LAS/LAZ/PLY file is one scan) or a TOML job list.

    Finished jobs are skipped on a rerun; a failed job is recorded and the rest go on; the exit code
    is 1 if any job failed.
    """
    with outcome_logged(log_json, jobs=str(jobs)):
        batch_jobs(jobs, out_dir, ratio, method, params, config, workers, memory_limit, scheduler, scratch, manifest,
                   overwrite, log_json)


def batch_jobs(jobs: Path, out_dir: Path | None, ratio: float | None, method: str | None, params: tuple[str, ...],
               config: str | None, workers: int | None, memory_limit: str | None, scheduler: str | None,
               scratch: Path | None, manifest: Path | None, overwrite: bool, log_json: bool) -> None:
    """`pipeline batch`'s work (see batch_command), its events logged as they come."""
    from pipeline.apps.batch import Manifest, jobs_from_folder, jobs_from_toml, run_batch

    flags = {name: value for name, value in dict(ratio=ratio, method=method, config=config, workers=workers,
                                                  memory_limit=memory_limit,
                                                  method_parameters=parse_parameters(params) or None).items()
             if value is not None}
    if jobs.is_dir():
        if out_dir is None:
            raise PipelineError(f"{jobs}: a folder of scans needs --out-dir")
        if ratio is None:
            raise PipelineError(f"{jobs}: a folder of scans needs --ratio")
        job_list = jobs_from_folder(jobs, out_dir, flags)
    elif jobs.is_file():
        job_list = jobs_from_toml(jobs, out_dir, flags)
    else:
        raise PipelineError(f"{jobs}: no such job file or folder")
    default_manifest = out_dir / "batch-manifest.json" if out_dir else jobs.with_suffix(".manifest.json")
    log = log_json_line if log_json else log_human_line
    note_worker_cap(job_list[0].config.workers, scheduler)
    summary = run_batch(job_list, Manifest(manifest or default_manifest), log, overwrite, scheduler, scratch,
                        Progress.for_terminal(log_json=log_json))
    log({"event": "batch", "done": summary.done, "skipped": summary.skipped, "failed": len(summary.failed)})
    if summary.failed:
        sys.exit(1)


@contextmanager
def outcome_logged(log_json: bool, **event: Any) -> Iterator[None]:
    """With --log-json, a command that does not finish still ends its stdout with one JSON line, `event` and: a
    `stopped` one (Ctrl-C, SIGTERM, or an error after one) with the shell's exit code, or a `failed` one with the
    one-line error that stderr shows. Only a PipelineError was logged: a stop, a file-system error or a crash
    left stdout without an outcome."""
    try:
        yield
    except SystemExit:
        raise
    except BaseException as exc:
        if log_json:
            stop = exc if isinstance(exc, KeyboardInterrupt) else STOPS[-1] if STOPS else None
            if stop is not None:
                log_json_line({"event": "stopped", **event, "error": str(exc) or "interrupted",
                               "exit_code": signal_exit_code(stop)})
            else:
                error = file_system_error(exc) if isinstance(exc, OSError) else exc
                said = str(error) if isinstance(error, PipelineError) else f"{type(exc).__name__}: {exc}"
                log_json_line({"event": "failed", **event, "error": said})
        raise


def log_json_line(event: dict) -> None:
    """One event as a JSON line with a UTC timestamp."""
    stamp = datetime.now(timezone.utc).isoformat(timespec="milliseconds")
    click.echo(json.dumps({"time": stamp, **event}))


def log_human_line(event: dict) -> None:
    """One batch event as a short line for a person."""
    kind = event["event"]
    if kind == "batch":
        click.echo(f"batch: {event['done']} done, {event['skipped']} already done, {event['failed']} failed")
    elif kind == "done":
        click.echo(f"done {event['output']}: {event['output_points']:,} of {event['input_points']:,} points "
                   f"({event['seconds']:.1f} s)")
    elif kind == "failed":
        click.echo(f"failed {event['output']}: {event['error']}", err=True)
    elif kind == "skipped":
        click.echo(f"skipped {event['output']}: already done")


@cli.command("info")
@click.argument("input_file", metavar="INPUT", type=click.Path(path_type=Path))
@click.option("--json", "as_json", is_flag=True, help="Print the summary as JSON.")
@click.option("--header-only", is_flag=True, help="Skip counting classes and returns (reads only the header).")
def info_command(input_file: Path, as_json: bool, header_only: bool) -> None:
    """Summarise INPUT: points, format, bounds, CRS with EPSG and units, density, size, class and return counts."""
    from pipeline.apps.scan_summary import format_summary, summarize

    summary = summarize(input_file, count_points=not header_only)
    click.echo(json.dumps(summary, indent=2) if as_json else format_summary(summary))


@cli.command("eval")
@click.argument("reference", type=click.Path(path_type=Path))
@click.argument("candidates", metavar="CANDIDATE...", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--json", "as_json", is_flag=True, help="Print the metrics as JSON.")
@click.option("--sample", type=int, default=DEFAULT_SAMPLE, show_default=True,
              help="Evaluate on seeded whole grid cells holding about this many reference points; 0: every point.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the sample.")
def eval_command(reference: Path, candidates: tuple[Path, ...], as_json: bool, sample: int, seed: int) -> None:
    """Score CANDIDATE outputs (LAS/LAZ/PLY/zarr) against REFERENCE: CD, Hausdorff, NC, CE, RE, SDM."""
    from pipeline.apps.scoring import evaluate, format_scores, reference_json, score_json

    ref, scores = evaluate(reference, list(candidates), sample, seed, Progress.for_terminal())
    click.echo(json.dumps({**reference_json(ref), "candidates": [score_json(s) for s in scores]}, indent=2)
               if as_json else format_scores(ref, scores))


@cli.command("compare")
@click.argument("input_file", metavar="INPUT", type=click.Path(path_type=Path))
@click.option("--ratios", default="0.2,0.1,0.05", show_default=True, help="Comma-separated ratios to keep.")
@click.option("--methods", default="learned,fps,voxel,random,tcp", show_default=True,
              help="Comma-separated methods to run.")
@click.option("--out-dir", type=click.Path(path_type=Path), default=Path("compare"), show_default=True,
              help="Folder for compare.md, compare.json, the plots and the simplified scans (runs/).")
@click.option("--workers", "-w", type=int, default=2, show_default=True, help="Dask worker processes per run.")
@click.option("--sample", type=int, default=DEFAULT_SAMPLE, show_default=True,
              help="Evaluate on seeded whole grid cells holding about this many input points; 0: every point.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the runs and of the sample.")
@click.option("--html", is_flag=True, help="Also write compare.html: the `pipeline report` page of every run.")
def compare_command(input_file: Path, ratios: str, methods: str, out_dir: Path, workers: int, sample: int,
                    seed: int, html: bool) -> None:
    """Simplify INPUT with each method at each ratio and compare them: table, JSON, plots, a region view."""
    from pipeline.apps.comparison import RunOptions, compare, parse_list, parse_ratios

    written = compare(input_file, parse_ratios(ratios), parse_list(methods, "--methods"), out_dir,
                      RunOptions(workers=workers, seed=seed, progress=Progress.for_terminal()), sample, html)
    click.echo("\n".join(str(path) for path in written))


@cli.command("report")
@click.argument("source", type=click.Path(path_type=Path))
@click.argument("outputs", metavar="OUTPUT...", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--output", "-o", "page", type=click.Path(path_type=Path), default=Path("report.html"),
              show_default=True, help="The HTML page (the density maps also go beside it as NAME.density.png).")
@click.option("--region", default=None, metavar="X,Y,SIZE",
              help="Show this square in 3-D: centre and side in the scan's units. [default: the most structured cell]")
@click.option("--color", type=click.Choice(COLORS), default="elevation",
              show_default=True, help="What colours the 3-D points (one scale, fixed from the source).")
@click.option("--sample", type=int, default=DEFAULT_SAMPLE, show_default=True,
              help="Evaluate on seeded whole grid cells holding about this many source points; 0: every point.")
@click.option("--overwrite", is_flag=True, help="Replace an existing page and its PNG.")
def report_command(source: Path, outputs: tuple[Path, ...], page: Path, region: str | None, color: str,
                   sample: int, overwrite: bool) -> None:
    """One self-contained HTML page judging OUTPUT(s) against SOURCE: a before/after 3-D view of one region,
    a kept-to-expected density map per output, the metrics with units, and how each output was made."""
    from pipeline.apps.report import write_report
    from pipeline.apps.visual.report_region import parse_region

    click.echo(write_report(source, list(outputs), page, parse_region(region) if region else None, color, sample,
                            overwrite=overwrite))


for extra in (demo_command, train_command, train_detail_command):
    cli.add_command(extra)


def main() -> None:
    """Console-script entry point. Once the command has ended (its outputs closed, its streams flushed),
    the process exits without Python's teardown of its ~1,100 modules: 0.25 s, a tenth of a small run."""
    try:
        cli(prog_name="pipeline")
        code = 0
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else 0 if exc.code is None else 1
        if isinstance(exc.code, str):
            click.echo(exc.code, err=True)
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except OSError:  # a reader that closed the pipe (`pipeline info | head -1`) wants no more
            pass
    os._exit(code)


if __name__ == "__main__":
    main()
