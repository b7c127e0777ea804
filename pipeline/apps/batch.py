"""`pipeline batch`: many scans on one cluster, with a manifest of what finished and what failed.

A job list is a folder (every LAS/LAZ/PLY file in it is one scan) or a TOML file:

    [defaults]               # any run setting, plus `config` (a preset or TOML file) and `out_dir`
    ratio = 0.1
    out_dir = "small/"
    [[job]]
    input = "a.laz"          # a path, or a list of paths that form one scan
    output = "small/a.laz"   # optional: <out_dir>/<stem>.simplified.<las|laz>
    ratio = 0.05             # optional per-job settings (a job's ratio or levels replace the defaults' both)

The manifest (JSON, rewritten atomically after each job) records per output: done (with counts and
the run key) or failed (with the one-line error). A rerun skips jobs done with the same key whose
output exists, and retries the rest.
"""
from __future__ import annotations

import json
import os
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from pipeline.config import RunConfig, build_config, checked_settings
from pipeline.engine.execute import cluster
from pipeline.engine.runner import default_output, run_scan, written_paths
from pipeline.engine.workdir import run_key, write_atomically
from pipeline.errors import PipelineError
from pipeline.io.output_guard import is_same_file
from pipeline.progress import Progress

SCAN_SUFFIXES = (".las", ".laz", ".ply")


@dataclass(frozen=True)
class BatchJob:
    """One scan of the batch: its files, where it goes and its settings."""

    inputs: tuple[Path, ...]
    output: Path
    config: RunConfig


@dataclass
class BatchSummary:
    """How many jobs were done, skipped as already done, and failed."""

    done: int = 0
    skipped: int = 0
    failed: list[str] = field(default_factory=list)


def jobs_from_folder(folder: Path, out_dir: Path, settings: dict[str, Any]) -> list[BatchJob]:
    """Every scan file in `folder` (sorted) as one job writing to `out_dir`; when `out_dir` is the folder
    itself, files named as the outputs of other files there are the batch's own results, not scans."""
    files = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in SCAN_SUFFIXES)
    if out_dir.is_dir() and is_same_file(out_dir, folder):
        outputs = {default_output(path).name for path in files}
        files = [path for path in files if path.name not in outputs]
    if not files:
        raise PipelineError(f"{folder}: no .las, .laz or .ply files")
    settings = dict(settings)  # the caller's flags stay as given
    config = build_config(settings.pop("config", None), **settings)
    return [BatchJob((path,), out_dir / default_output(path).name, config) for path in files]


def jobs_from_toml(path: Path, out_dir: Path | None, overrides: dict[str, Any]) -> list[BatchJob]:
    """The [[job]] entries of a TOML job list, each over [defaults], flags winning over both."""
    try:
        spec = tomllib.loads(path.read_text())
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise PipelineError(f"{path}: not a readable TOML job list ({exc})") from exc
    defaults, entries = spec.get("defaults", {}), spec.get("job", [])
    if not isinstance(defaults, dict):
        raise PipelineError(f"{path}: [defaults] must be a table of settings, got {defaults!r}")
    if not isinstance(entries, list) or not all(isinstance(entry, dict) for entry in entries):
        raise PipelineError(f"{path}: jobs must be [[job]] tables, got {entries!r}")
    if not entries:
        raise PipelineError(f"{path}: no [[job]] entries")
    defaults = dict(defaults)
    base = path.parent
    folder = out_dir or (base / text_value(defaults.pop("out_dir"), f"{path}: [defaults] out_dir")
                         if "out_dir" in defaults else None)
    defaults.pop("out_dir", None)
    jobs = []
    for number, entry in enumerate(entries, start=1):
        where = f"{path}: job {number}"
        entry = dict(entry)
        if "input" not in entry:
            raise PipelineError(f"{where} has no input")
        names = entry.pop("input")
        names = [names] if isinstance(names, str) else names
        if not isinstance(names, list) or not names:
            raise PipelineError(f"{where}: input must be a path or a list of paths, got {names!r}")
        inputs = tuple(base / text_value(name, f"{where} input") for name in names)
        output = entry.pop("output", None)
        if output is None and folder is None:
            raise PipelineError(f"{where} has no output and there is no out_dir")
        target = base / text_value(output, f"{where} output") if output is not None else folder / default_output(inputs[0]).name
        own = job_settings(entry, where)
        shared = {k: v for k, v in job_settings(defaults, f"{path}: [defaults]").items() if k not in sizes_of(own)}
        settings = {**shared, **own, **overrides}
        try:
            jobs.append(BatchJob(inputs, target, build_config(settings.pop("config", None), **settings)))
        except PipelineError as exc:
            raise PipelineError(f"{where}: {exc}") from None
    return jobs


def sizes_of(settings: dict[str, Any]) -> set[str]:
    """The output-size settings a job's own `ratio` or `levels` replaces in [defaults]: both (the first level is
    the ratio, so the defaults' other one would disagree with it), else none."""
    return {"ratio", "levels"} if settings.keys() & {"ratio", "levels"} else set()


def job_settings(table: dict[str, Any], where: str) -> dict[str, Any]:
    """Run settings of a job list's table, checked (`config`, a preset or file, may sit beside them)."""
    settings = dict(table)
    preset = settings.pop("config", None)
    checked_settings(settings, where)
    return settings if preset is None else {**settings, "config": text_value(preset, f"{where} config")}


def text_value(value: Any, where: str) -> str:
    """A non-empty string from a job list (a path), else one line naming where it sits."""
    if not isinstance(value, str) or not value.strip():
        raise PipelineError(f"{where} must be a non-empty path, got {value!r}")
    return value


def check_batch_outputs(jobs: list[BatchJob]) -> None:
    """Before any job runs: no two jobs write one output, and no job writes over any job's input."""
    inputs = [path for job in jobs for path in job.inputs]
    for number, job in enumerate(jobs):
        for other in jobs[:number]:
            if job.output.resolve() == other.output.resolve() or is_same_file(job.output, other.output):
                raise PipelineError(f"{job.output}: written by two jobs ({', '.join(map(str, other.inputs))} and "
                                    f"{', '.join(map(str, job.inputs))}); give them different outputs")
        for path in inputs:
            if job.output.resolve() == path.resolve() or is_same_file(job.output, path):
                raise PipelineError(f"{job.output}: the output of {', '.join(map(str, job.inputs))} is also an "
                                    "input of the batch; write the results elsewhere (--out-dir)")


class Manifest:
    """Per-output records of a batch, kept in a JSON file."""

    def __init__(self, path: Path) -> None:
        self.path = path
        try:
            self.entries: dict[str, dict[str, Any]] = json.loads(path.read_text()) if path.is_file() else {}
        except (OSError, ValueError) as exc:
            raise PipelineError(f"{path}: unreadable batch manifest ({exc}); move it aside to start afresh") from exc
        if not (isinstance(self.entries, dict) and all(isinstance(e, dict) for e in self.entries.values())):
            raise PipelineError(f"{path}: not a batch manifest (a JSON object of per-output records); "
                                "move it aside to start afresh")

    def name(self, output: Path) -> str:
        """The record name of an output: its path from the manifest's folder, however the command spelled it (a
        batch run from another folder, or with --out-dir absolute, found nothing done), and the same after the
        folder moves."""
        return os.path.relpath(output.resolve(), self.path.parent.resolve())

    def wrote(self, job: BatchJob) -> bool:
        """Whether an earlier batch finished this job's output (so replacing it needs no --overwrite)."""
        return self.entries.get(self.name(job.output), {}).get("status") == "done"

    def is_done(self, job: BatchJob, key: str) -> bool:
        """Finished earlier with the same inputs and settings, and the output is still there."""
        entry = self.entries.get(self.name(job.output), {})
        return (entry.get("status") == "done" and entry.get("key") == key
                and all(path.exists() for path in written_paths(job.output, job.config.levels)))

    def record(self, job: BatchJob, entry: dict[str, Any]) -> None:
        """Store one job's outcome and rewrite the file atomically."""
        self.entries[self.name(job.output)] = {"inputs": [str(p) for p in job.inputs], **entry}
        self.path.parent.mkdir(parents=True, exist_ok=True)
        write_atomically(self.path, lambda tmp: tmp.write_text(json.dumps(self.entries, indent=2)))


def run_batch(jobs: list[BatchJob], manifest: Manifest, log: Callable[[dict[str, Any]], None],
              overwrite: bool = False, scheduler: str | None = None, scratch: Path | None = None,
              progress: Progress = Progress()) -> BatchSummary:
    """Run every job not already done on one cluster; a failed job is recorded and the batch goes on.
    `progress` shows each run's phases and a step per job."""
    check_batch_outputs(jobs)
    summary = BatchSummary()
    first = jobs[0].config
    with cluster(first.workers, first.memory_limit, scheduler) as client, \
            progress.phase("batch", len(jobs), unit="job") as batch_phase:
        for job in jobs:
            event = {"input": [str(p) for p in job.inputs], "output": str(job.output)}
            key = run_key(job.inputs, job.config) if all(p.is_file() for p in job.inputs) else ""
            if key and manifest.is_done(job, key):
                summary.skipped += 1
                log({"event": "skipped", **event})
                batch_phase.update(1)
                continue
            log({"event": "started", **event})
            started = time.time()
            ours = manifest.wrote(job)
            try:
                job.output.parent.mkdir(parents=True, exist_ok=True)
                report = run_scan(list(job.inputs), job.output, job.config, overwrite=overwrite or ours,
                                  scratch=scratch, client=client, progress=progress)
            except Exception as exc:  # one scan's failure, whatever it is, must not stop the nightly batch
                message = str(exc) if isinstance(exc, PipelineError) else f"{type(exc).__name__}: {exc}"
                summary.failed.append(str(job.output))
                manifest.record(job, {"status": "failed", "error": message, "key": key})
                log({"event": "failed", **event, "error": message, "seconds": round(time.time() - started, 3)})
                batch_phase.update(1)
                continue
            summary.done += 1
            batch_phase.update(1, report.input_points)
            outcome = {"status": "done", "key": key, "input_points": report.input_points,
                       "output_points": report.output_points, "seconds": round(report.seconds, 3)}
            manifest.record(job, outcome)
            log({"event": "done", **event, **{k: v for k, v in outcome.items() if k not in ("status", "key")}})
    return summary
