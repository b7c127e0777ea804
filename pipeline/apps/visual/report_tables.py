"""The report's tables as HTML: metrics with units, each output's density-map spread, and how each output was
made (its provenance record) with its size on disk."""
from __future__ import annotations

import html
import json
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from pipeline.apps.scan_summary import human_size
from pipeline.apps.scoring import METRIC_COLUMNS, Reference, Score, metric_cells
from pipeline.apps.visual.density_map import DensityMap
from pipeline.io.points import zarr_group
from pipeline.io.provenance import read_provenance
from pipeline.io.scan import open_source

UNITLESS = "–"


def html_table(titles: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    """An HTML table, every cell escaped; the first column left-aligned, the others right-aligned."""
    head = "".join(f"<th>{html.escape(t)}</th>" for t in titles)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(cell)}</td>" for cell in row) + "</tr>" for row in rows)
    return f'<table class="numbers"><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>'


def size_on_disk(path: Path) -> int:
    """Bytes of a file, or of every file in a zarr store."""
    if path.is_dir():
        return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())
    return path.stat().st_size


def provenance_of(path: Path) -> dict[str, Any] | None:
    """The run record an output carries (LAS/LAZ VLR or zarr attribute `provenance`), or None."""
    if path.suffix.lower() == ".zarr":
        record = zarr_group(path).attrs.get("provenance")
        return json.loads(record) if isinstance(record, str) else record
    return read_provenance(open_source(path).header)


def metrics_table(reference: Reference, scores: Sequence[Score], labels: Sequence[str]) -> str:
    """A row per output: points, share kept, size, then every metric; the titles give the units."""
    unit = reference.unit.label
    units = {"chamfer": f"{unit}²", "hausdorff": unit}
    titles = ["output", "points", "kept", "size",
              *(f"{title} ({units.get(field, UNITLESS)})" for title, field, _ in METRIC_COLUMNS)]
    rows = [[label, f"{s.points:,}", f"{s.points / reference.points:.3g}", human_size(size_on_disk(s.path)),
             *metric_cells(s.quality)] for label, s in zip(labels, scores)]
    return html_table(titles, rows)


def spread_table(maps: Sequence[DensityMap], labels: Sequence[str]) -> str:
    """A row per output: how evenly it kept its share over the cells the source fills."""
    rows = []
    for label, density in zip(labels, maps):
        ratio = density.ratio[np.isfinite(density.ratio)]
        p5, median, p95 = np.percentile(ratio, [5, 50, 95])
        rows.append([label, f"{len(ratio):,}", f"{median:.2f}", f"{p5:.2f} .. {p95:.2f}",
                     f"{np.mean(ratio < 0.5):.1%}", f"{np.mean(ratio > 2):.1%}", f"{np.mean(ratio == 0):.1%}"])
    return html_table(["output", "cells", "median", "5th .. 95th percentile", "under 0.5", "over 2", "empty"], rows)


def provenance_table(scores: Sequence[Score], labels: Sequence[str]) -> str:
    """A row per output: file, method, ratio, software, date, weights, settings and sources from its run record."""
    rows = []
    for label, s in zip(labels, scores):
        record = provenance_of(s.path)
        if record is None:
            rows.append([label, str(s.path), "no run record (not written by lidar-simplify)", "", "", "", "", ""])
            continue
        settings = ", ".join(f"{k}={v}" for k, v in sorted((record.get("settings") or {}).items()))
        rows.append([label, str(s.path), str(record.get("method")), f"{record.get('ratio')}",
                     f"{record.get('software')} {record.get('version')}, {record.get('created')}",
                     str(record.get("model_weights") or UNITLESS), settings,
                     ", ".join(str(source) for source in record.get("sources") or [])])
    return html_table(["output", "file", "method", "ratio", "made by", "weights", "settings (lengths in metres)",
                       "sources"], rows)
