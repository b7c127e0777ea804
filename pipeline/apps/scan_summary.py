"""`pipeline info` (and `pipeline.info`): what `pdal info --summary` and `lasinfo` users look for in a scan file: its header,
CRS (EPSG, horizontal and vertical units), point density, file size, and class and return counts
counted from the points (a header's per-return counts may lie)."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import laspy
import numpy as np

from pipeline.engine.classes import class_histogram
from pipeline.io.crs import axis_unit, crs_label, crs_wkt, length_unit, parsed_crs
from pipeline.io.provenance import read_provenance
from pipeline.io.scan import open_source

COUNT_CHUNK = 2_000_000  # points decoded at a time while counting classes and returns


def point_counts(path: Path) -> tuple[dict[int, int], dict[int, int]]:
    """Points per classification code and per return number, counted in chunks over the whole file. The
    records are decoded as a run decodes them, but not held to the header's bounds: a file whose bounds
    are wrong (which a run measures anew) or that holds no point is described, not refused."""
    source = open_source(path)
    classes = np.zeros(256, dtype=np.int64)
    returns = np.zeros(16, dtype=np.int64)
    for start in range(0, source.point_count, COUNT_CHUNK):
        records = source.read(start, min(COUNT_CHUNK, source.point_count - start))
        classes += class_histogram(records)
        returns += np.bincount(laspy.PackedPointRecord(records, source.header.point_format)["return_number"],
                               minlength=16)
    return ({int(c): int(classes[c]) for c in np.flatnonzero(classes)},
            {int(r): int(returns[r]) for r in np.flatnonzero(returns)})


def summarize(path: str | Path, count_points: bool = True) -> dict[str, Any]:
    """Header, CRS, units, density and (unless `count_points` is False) class and return counts of one file."""
    path = Path(path)
    source = open_source(path)
    header = source.header
    crs = parsed_crs(header)
    unit = length_unit(header)
    lo, hi = np.asarray(header.mins, float), np.asarray(header.maxs, float)
    area = float(np.prod(hi[:2] - lo[:2]))
    summary: dict[str, Any] = {
        "file": str(path),
        "file_size": path.stat().st_size,
        "points": source.point_count,
        "las_version": str(header.version),
        "point_format": header.point_format.id,
        "compressed": bool(header.are_points_compressed),
        "copc": any(v.user_id == "copc" for v in header.vlrs),
        "generating_software": header.generating_software,
        "creation_date": header.creation_date.isoformat() if header.creation_date and header.creation_date.year > 1 else None,
        "bounds": {"min": lo.tolist(), "max": hi.tolist()},
        "scale": [float(v) for v in header.scales],
        "offset": [float(v) for v in header.offsets],
        "crs": crs_label(header),
        "epsg": crs.to_epsg() if crs is not None else None,
        "crs_wkt": crs_wkt(header),
        "horizontal_unit": unit.name,
        "horizontal_unit_assumed": unit.assumed,
        "metres_per_unit": unit.metres,
        "vertical_unit": axis_unit(crs, "z"),
        "area": area,
        "density": source.point_count / area if area > 0 else None,
        "dimensions": list(header.point_format.dimension_names),
        "extra_dimensions": list(header.point_format.extra_dimension_names),
        "vlrs": [f"{v.user_id}/{v.record_id}" for v in header.vlrs],
        "provenance": read_provenance(header),
    }
    if count_points:
        summary["class_counts"], summary["return_counts"] = point_counts(path)
    return summary


def format_summary(summary: dict[str, Any]) -> str:
    """Human-readable lines of a summary."""
    lo, hi = summary["bounds"]["min"], summary["bounds"]["max"]
    unit = summary["horizontal_unit"] + (" (assumed)" if summary["horizontal_unit_assumed"] else "")
    density = f"{summary['density']:,.2f} points per square {summary['horizontal_unit']} over the bounding box " \
        f"({summary['area']:,.1f} square {summary['horizontal_unit']})" if summary["density"] else "n/a (flat bounds)"
    kind = "COPC" if summary["copc"] else "LAZ" if summary["compressed"] else "uncompressed"
    lines = [
        f"file:          {summary['file']} ({human_size(summary['file_size'])})",
        f"points:        {summary['points']:,}",
        f"LAS version:   {summary['las_version']}  point format {summary['point_format']}  ({kind})",
        f"written by:    {summary['generating_software'] or 'unknown'} on {summary['creation_date'] or 'unknown date'}",
        f"bounds:        x {lo[0]:.3f} .. {hi[0]:.3f}   y {lo[1]:.3f} .. {hi[1]:.3f}   z {lo[2]:.3f} .. {hi[2]:.3f}",
        f"scale:         {' '.join(f'{v:g}' for v in summary['scale'])}",
        f"offset:        {' '.join(f'{v:g}' for v in summary['offset'])}",
        f"CRS:           {summary['crs']}",
        f"units:         horizontal {unit}, vertical {summary['vertical_unit'] or 'not given by the CRS'}",
        f"density:       {density}",
    ]
    if "class_counts" in summary:
        lines.append("classes:       " + (", ".join(f"{c}: {n:,}" for c, n in summary["class_counts"].items())
                                          or "none (no points)"))
        lines.append("returns:       " + (", ".join(f"{r}: {n:,}" for r, n in summary["return_counts"].items())
                                          or "none (no points)"))
    lines += [f"dimensions:    {', '.join(summary['dimensions'])}",
              f"VLRs:          {', '.join(summary['vlrs']) or 'none'}"]
    if summary["provenance"]:
        record = summary["provenance"]
        weights = f" (weights {record['model_weights']})" if record.get("model_weights") else ""
        lines.append(f"simplified:    by {record['software']} {record['version']} with {record['method']}{weights} "
                     f"at ratio {record['ratio']:g}")
    return "\n".join(lines)


def human_size(count: int) -> str:
    """Bytes as a short figure: 12.3 MB."""
    value = float(count)
    for unit in ("B", "kB", "MB", "GB"):
        if value < 1000:
            return f"{value:.3g} {unit}" if unit != "B" else f"{count} B"
        value /= 1000
    return f"{value:.3g} TB"
