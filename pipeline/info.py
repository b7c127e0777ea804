"""`pipeline info`: a header summary of a scan file, like `pdal info --summary`."""
from __future__ import annotations

from pathlib import Path
from typing import Any

from pipeline.crs import crs_wkt
from pipeline.scan import open_source


def summarize(path: str | Path) -> dict[str, Any]:
    """Points, LAS version, point format, bounds, scale/offset, CRS and dimensions of one file."""
    source = open_source(Path(path))
    header = source.header
    return {
        "file": str(path),
        "points": source.point_count,
        "las_version": str(header.version),
        "point_format": header.point_format.id,
        "compressed": Path(path).suffix.lower() == ".laz",
        "bounds": {"min": [float(v) for v in header.mins], "max": [float(v) for v in header.maxs]},
        "scale": [float(v) for v in header.scales],
        "offset": [float(v) for v in header.offsets],
        "crs_wkt": crs_wkt(header),
        "dimensions": list(header.point_format.dimension_names),
        "extra_dimensions": list(header.point_format.extra_dimension_names),
        "vlrs": [f"{v.user_id}/{v.record_id}" for v in header.vlrs],
    }


def format_summary(summary: dict[str, Any]) -> str:
    """Human-readable lines of a summary."""
    crs = summary["crs_wkt"]
    crs_line = (crs.split('"')[1] if crs and '"' in crs else crs) or "none"
    lo, hi = summary["bounds"]["min"], summary["bounds"]["max"]
    lines = [
        f"file:          {summary['file']}",
        f"points:        {summary['points']:,}",
        f"LAS version:   {summary['las_version']}  point format {summary['point_format']}"
        f"{'  (LAZ)' if summary['compressed'] else ''}",
        f"bounds:        x {lo[0]:.3f} .. {hi[0]:.3f}   y {lo[1]:.3f} .. {hi[1]:.3f}   z {lo[2]:.3f} .. {hi[2]:.3f}",
        f"scale:         {' '.join(f'{v:g}' for v in summary['scale'])}",
        f"offset:        {' '.join(f'{v:g}' for v in summary['offset'])}",
        f"CRS:           {crs_line}",
        f"dimensions:    {', '.join(summary['dimensions'])}",
        f"VLRs:          {', '.join(summary['vlrs']) or 'none'}",
    ]
    return "\n".join(lines)
