"""`pipeline report`: one self-contained HTML page (plotly's script inlined, so it opens offline) on which a
surveyor can judge simplified scans against their source: a before/after 3-D view of one region, a
kept-to-expected density map per output, the metrics with units, and how each output was made.
The density maps are also written as a PNG beside the page, for Markdown.
"""
from __future__ import annotations

import html
from datetime import datetime, timezone
from pathlib import Path
from typing import Sequence

import plotly.graph_objects as go

from pipeline.apps.defaults import COLORS, DEFAULT_SAMPLE
from pipeline.apps.scoring import Reference, Score, evaluate, sample_note
from pipeline.apps.visual.density_map import density_maps
from pipeline.apps.visual.density_plots import density_figure, density_png
from pipeline.apps.visual.report_region import Region, find_region, sample_region
from pipeline.apps.visual.report_tables import metrics_table, provenance_table, spread_table
from pipeline.apps.visual.view3d import SYNC_CAMERAS, ColourScale, region_figure
from pipeline.errors import PipelineError
from pipeline.io.atomic import atomic_output
from pipeline.io.output_guard import check_output
from pipeline.io.crs import axis_unit, parsed_crs
from pipeline.io.provenance import software_name
from pipeline.io.scan import open_source

PANEL_POINTS = 60_000  # points drawn per 3-D scene at most
VIEW_POINTS = 400_000  # and in all scenes together, so a page of many outputs stays light in a browser
STYLE = """body{font-family:system-ui,sans-serif;margin:1.5em auto;max-width:1400px;color:#222}
table.numbers{border-collapse:collapse;font-size:0.9em;margin:0.5em 0}
table.numbers th,table.numbers td{border:1px solid #ccc;padding:0.25em 0.6em;text-align:right}
table.numbers td:first-child,table.numbers th:first-child{text-align:left}
p.note{color:#555;font-size:0.9em}"""


def write_report(source: Path, outputs: Sequence[Path], path: Path, region: Region | None = None,
                 color: str = "elevation", sample: int = DEFAULT_SAMPLE, seed: int = 0,
                 overwrite: bool = False) -> Path:
    """Score `outputs` against `source` (on `sample` reference points, see pipeline.apps.scoring) and write the
    HTML report to `path` (and its density-map PNG beside it); return `path`. Neither may be one of the files
    reported on, nor replace an existing file without `overwrite` (nor, even with it, one that is not a page or
    PNG), as a run's output may not.

    `region` is the square shown in 3-D (default: the source's cell with the most structure); `color` is
    elevation, classification or rgb.
    """
    if not outputs:
        raise PipelineError("give at least one output to report on")
    read = [Path(source), *map(Path, outputs)]
    check_output(Path(path), read, overwrite, (".html",))
    check_output(density_png_path(Path(path)), read, overwrite, (".png",))
    reference, scores = evaluate(Path(source), [Path(o) for o in outputs], sample, seed)
    return render_report(reference, scores, [Path(o).name for o in outputs], Path(path), region, color)


def render_report(reference: Reference, scores: Sequence[Score], labels: Sequence[str], path: Path,
                  region: Region | None = None, color: str = "elevation") -> Path:
    """The report of already scored outputs (`labels` name them in every section), written atomically."""
    if color not in COLORS:
        raise PipelineError(f"--color must be one of {', '.join(COLORS)}, got {color!r}")
    source = reference.path
    unit = reference.unit.label
    region = region or find_region(source)
    view = region_view(source, scores, labels, region, color, unit)
    maps = density_maps(source, [s.path for s in scores])
    png = density_png(maps, labels, unit, density_png_path(path))
    cell = f"{maps[0].grid.side:.3g} {unit}"
    sections = [
        f"<h1>Quality report: {html.escape(source.name)}</h1>",
        f'<p class="note">{html.escape(sample_note(reference))}. Made by {html.escape(software_name())} on '
        f"{datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC.</p>",
        "<h2>Metrics</h2>", metrics_table(reference, scores, labels),
        f"<h2>Region {html.escape(region.describe())} (centre x, y and side in {html.escape(unit)}), "
        f"coloured by {color}</h2>",
        '<p class="note">Drag to turn: every scene turns with it. One colour scale, fixed from the source.</p>',
        figure_html(view, "region-view", include_plotlyjs=True, post_script=SYNC_CAMERAS),
        f"<h2>Kept-to-expected density (cells of {html.escape(cell)})</h2>",
        '<p class="note">Points an output kept in each cell divided by its share (the ratio it kept times the '
        "source's points there): 1 (white) is even; red kept less, blue more; blank cells hold no source point. "
        f'Also as <a href="{html.escape(png.name)}">{html.escape(png.name)}</a>.</p>',
        spread_table(maps, labels), figure_html(density_figure(maps, labels, unit), "density-maps"),
        "<h2>How each output was made</h2>", provenance_table(scores, labels),
    ]
    page = (f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8"><title>Quality report: '
            f"{html.escape(source.name)}</title><style>{STYLE}</style></head><body>\n"
            + "\n".join(sections) + "\n</body></html>\n")
    with atomic_output(path) as temporary:
        temporary.write_text(page, encoding="utf-8")
    return path


def density_png_path(path: Path) -> Path:
    """Where the report at `path` puts its density-map PNG: report.html -> report.density.png."""
    return path.with_suffix(".density.png")


def region_view(source: Path, scores: Sequence[Score], labels: Sequence[str], region: Region, color: str,
                unit: str) -> go.Figure:
    """The 3-D figure: the source and every output in `region`, each subsampled to its share of the budget."""
    cap = min(PANEL_POINTS, VIEW_POINTS // (len(scores) + 1))
    source_sample = sample_region(source, region, color, cap)
    if source_sample.total == 0:
        raise PipelineError(f"{source}: no points in the region {region.describe()}")
    panels = [(f"source {source.name}", source_sample),
              *((label, sample_region(s.path, region, color, cap)) for label, s in zip(labels, scores))]
    z_unit = vertical_unit(source) or unit
    return region_figure(panels, region, ColourScale.of(source_sample, color, z_unit), unit, z_unit)


def vertical_unit(source: Path) -> str | None:
    """The unit of z a LAS/LAZ/PLY source's CRS names (a compound CRS's vertical part), or None."""
    return None if source.suffix.lower() == ".zarr" else axis_unit(parsed_crs(open_source(source).header), "z")


def figure_html(figure: go.Figure, div_id: str, include_plotlyjs: bool = False, post_script: str | None = None) -> str:
    """A figure as a <div> of the page; the first one carries plotly's script inline (no CDN: opens offline)."""
    return figure.to_html(full_html=False, include_plotlyjs=include_plotlyjs, div_id=div_id,
                          post_script=post_script, config={"displaylogo": False})
