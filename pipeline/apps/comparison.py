"""`pipeline compare`: simplify one scan with several methods at several ratios, score every result
against the scan, and write a Markdown table, JSON, a plot per metric and a picture of one region.

A method is a name mapped to a producer, a callable that writes the simplified cloud of an input at a
ratio; the tile simplifiers all go through the normal pipeline, every run on one Dask cluster (started
once: its workers keep torch and the model loaded). A method outside the pipeline (QEM on a mesh,
say) is one more entry in PRODUCERS.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Sequence

import numpy as np

from model.geometry import point_features
from model.rules import kept_count
from model.registry import METHODS
from pipeline.apps.defaults import DEFAULT_SAMPLE
from pipeline.apps.report import density_png_path, render_report
from pipeline.apps.scoring import (METRIC_COLUMNS, Reference, Score, check_sample, markdown_table, metric_cells,
                                   prepare_reference, reference_json, sample_note, score, score_json)
from pipeline.apps.visual.plots import Panel, metric_plot, region_view
from pipeline.config import build_config
from pipeline.engine.execute import cluster
from pipeline.engine.processes import importing_parents_script
from pipeline.engine.runner import run_scan
from pipeline.errors import PipelineError
from pipeline.io.points import Cells, covering_grid, load_xyz, point_count
from pipeline.progress import Progress

if TYPE_CHECKING:
    from dask.distributed import Client

REGION_POINTS = 20_000  # reference points in the pictured cell, on average over the grid: a few buildings' worth


@dataclass(frozen=True)
class RunOptions:
    """What every producer is told besides input, output and ratio."""

    workers: int = 1
    seed: int = 0
    progress: Progress = field(default_factory=Progress)  # a step per run (method and ratio)


Producer = Callable[[Path, Path, float, RunOptions, "Client"], None]


def through_pipeline(method: str) -> Producer:
    """A producer running the pipeline with one of the tile simplifiers on the given cluster."""
    def produce(source: Path, output: Path, ratio: float, options: RunOptions, client: Client) -> None:
        config = build_config(ratio=ratio, method=method, workers=options.workers, seed=options.seed)
        run_scan([source], output, config, overwrite=True, client=client)

    return produce


PRODUCERS: dict[str, Producer] = {method: through_pipeline(method) for method in METHODS}


@dataclass(frozen=True)
class Entry:
    """One method at one ratio, scored."""

    method: str
    ratio: float
    score: Score


def parse_list(text: str, option: str) -> list[str]:
    """The comma-separated items of an option value, which must not be empty."""
    items = [item.strip() for item in text.split(",") if item.strip()]
    if not items:
        raise PipelineError(f"{option} needs at least one comma-separated value, got {text!r}")
    return items


def parse_ratios(text: str) -> list[float]:
    """Ratios such as '0.2,0.1,0.05', each in (0, 1]."""
    try:
        ratios = [float(item) for item in parse_list(text, "--ratios")]
    except ValueError:
        raise PipelineError(f"--ratios must be numbers such as 0.2,0.1,0.05, got {text!r}") from None
    bad = [r for r in ratios if not 0 < r <= 1]
    if bad:
        raise PipelineError(f"--ratios must each be in (0, 1], got {bad[0]!r}")
    return ratios


def compare(source: Path, ratios: Sequence[float], methods: Sequence[str], out_dir: Path,
            options: RunOptions = RunOptions(), sample: int = DEFAULT_SAMPLE, html: bool = False) -> list[Path]:
    """Run, score and report every method at every ratio; return the files written to `out_dir`
    (with `html`, also compare.html: the `pipeline report` page of every run, and its density-map PNG)."""
    if importing_parents_script():  # its runs share a local cluster, whose workers import the caller's script
        raise PipelineError("pipeline.compare was called while a worker process imported the script that started "
                            "it: call it under `if __name__ == \"__main__\":`")
    unknown = [m for m in methods if m not in PRODUCERS]
    if unknown:
        raise PipelineError(f"unknown method(s) {', '.join(unknown)}; known: {', '.join(PRODUCERS)}")
    if not source.exists():
        raise PipelineError(f"{source}: no such file")
    check_sample(sample)
    points = point_count(source)
    for ratio in ratios:  # every run's settings checked before the first run
        if kept_count(build_config(ratio=ratio).ratio, points) == 0:
            raise PipelineError(f"{source}: --ratio {ratio} keeps 0 of {points} points")
    runs = out_dir / "runs"
    runs.mkdir(parents=True, exist_ok=True)
    reference = prepare_reference(source, sample, options.seed, options.progress)
    entries = []
    with cluster(options.workers, build_config().memory_limit, None) as client, \
            options.progress.phase("compare: run and score", len(methods) * len(ratios), unit="run") as phase:
        for method in methods:
            for ratio in ratios:
                output = runs / f"{method}-{ratio:g}.laz"
                PRODUCERS[method](source, output, ratio, options, client)
                entries.append(Entry(method, ratio, score(reference, output)))
                phase.update(1, entries[-1].score.points)
    written = [write_markdown(reference, entries, out_dir), write_json(reference, entries, out_dir),
               *write_metric_plots(entries, out_dir), write_region(reference, entries, methods, ratios, out_dir)]
    if html:
        page = render_report(reference, [e.score for e in entries], [f"{e.method} {e.ratio:g}" for e in entries],
                             out_dir / "compare.html")
        written += [page, density_png_path(page)]
    return written


def write_markdown(reference: Reference, entries: Sequence[Entry], out_dir: Path) -> Path:
    """compare.md: the table (a row per method and ratio) and the figures."""
    titles = ["method", "ratio", "points", *(title for title, _, _ in METRIC_COLUMNS)]
    rows = [[e.method, f"{e.ratio:g}", f"{e.score.points:,}", *metric_cells(e.score.quality)] for e in entries]
    figures = "\n".join(f"![{title}]({field}.png)" for title, field, _ in METRIC_COLUMNS)
    text = (f"# Comparison on {reference.path.name}\n\n{sample_note(reference)}\n\n{markdown_table(titles, rows)}\n\n"
            f"{figures}\n\n![one region, coloured by mean curvature](region.png)\n")
    path = out_dir / "compare.md"
    path.write_text(text)
    return path


def write_json(reference: Reference, entries: Sequence[Entry], out_dir: Path) -> Path:
    """compare.json: the reference, the sample, and a record per method and ratio."""
    results = [{"method": e.method, "ratio": e.ratio, **score_json(e.score)} for e in entries]
    path = out_dir / "compare.json"
    path.write_text(json.dumps({**reference_json(reference), "results": results}, indent=2))
    return path


def write_metric_plots(entries: Sequence[Entry], out_dir: Path) -> list[Path]:
    """One PNG per metric against the ratio, a line per method."""
    paths = []
    for title, metric, _ in METRIC_COLUMNS:
        values: dict[str, dict[float, float]] = {}
        for e in entries:
            values.setdefault(e.method, {})[e.ratio] = getattr(e.score.quality, metric)
        paths.append(metric_plot(values, title, out_dir / f"{metric}.png"))
    return paths


def detailed_region(reference: Reference) -> Cells:
    """The grid cell (in file coordinates) holding the most mean curvature: dense and curved at once."""
    xyz = reference.xyz
    grid = covering_grid(xyz.min(axis=0), xyz.max(axis=0), max(1, len(xyz) // REGION_POINTS))
    weight = np.bincount(grid.keys(xyz), weights=reference.features.mean_curvature,
                         minlength=grid.shape[0] * grid.shape[1])
    return Cells(grid.origin + reference.centre[:2], grid.side, grid.shape, np.array([int(weight.argmax())]))


def write_region(reference: Reference, entries: Sequence[Entry], methods: Sequence[str], ratios: Sequence[float],
                 out_dir: Path) -> Path:
    """region.png: the most detailed cell as the reference and every result show it."""
    region = detailed_region(reference)
    inside = region.contains(reference.xyz + reference.centre)
    panels: dict[tuple[str, float], Panel] = {}
    for e in entries:
        xyz = load_xyz(e.score.path, region) - reference.centre
        panels[(e.method, e.ratio)] = (xyz, region_curvature(xyz))
    return region_view((reference.xyz[inside], reference.features.mean_curvature[inside]), panels, methods,
                       ratios, out_dir / "region.png")


def region_curvature(xyz: np.ndarray) -> np.ndarray:
    """Mean curvature of a result's points in the region; none for a result with no point there (a tiny ratio,
    a sparse or linear scan), where the kd-tree of point_features refuses an empty cloud: an empty panel then."""
    return point_features(xyz).mean_curvature if len(xyz) else np.zeros(0, dtype=np.float32)
