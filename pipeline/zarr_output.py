"""The zarr output: a zarr v3 group of one array per point dimension, with the run's metadata."""
from __future__ import annotations

from pathlib import Path
from typing import Iterable

import laspy
import numpy as np
import zarr

from pipeline.errors import PipelineError
from pipeline.output_meta import OutputMeta, TilePart
from pipeline.provenance import run_record

ZARR_CHUNK = 1_000_000


def zarr_dimensions(point_format: laspy.PointFormat) -> list[str]:
    """Array names of a zarr output: scaled x, y, z, then every other LAS dimension (extra bytes too)."""
    return ["x", "y", "z"] + [n for n in point_format.dimension_names if n not in ("X", "Y", "Z")]


def write_zarr(path: Path, header: laspy.LasHeader, total: int, parts: Iterable[TilePart], meta: OutputMeta) -> int:
    """One 1-D array per dimension, chunked along points, with CRS, provenance and a tile index in attributes."""
    group = zarr.open_group(str(path), mode="w", zarr_format=3)
    point_format = header.point_format
    names = zarr_dimensions(point_format)
    probe = laspy.ScaleAwarePointRecord.zeros(1, header=header)
    arrays = {name: group.create_array(name, shape=(total,), chunks=(min(ZARR_CHUNK, max(total, 1)),),
                                       dtype=np.asarray(probe[name]).dtype, dimension_names=["point"])
              for name in names}
    tile_index, start, written, pending = [], 0, 0, []

    def flush(final: bool) -> int:
        """Write whole chunks of the pending records (all of them when final); return the new write position."""
        records = np.concatenate(pending) if pending else np.empty(0, point_format.dtype())
        size = len(records) if final else len(records) // ZARR_CHUNK * ZARR_CHUNK
        record = laspy.ScaleAwarePointRecord(records[:size], point_format, header.scales, header.offsets)
        for name in names:
            arrays[name][written:written + size] = np.asarray(record[name])
        pending[:] = [records[size:]]
        return written + size

    for part in parts:
        tile_index.append({"tile": part.tile_id, "bounds": list(part.bounds), "start": start, "count": len(part.records)})
        start += len(part.records)
        pending.append(part.records)
        if start - written >= ZARR_CHUNK:
            written = flush(final=False)
    written = flush(final=True)
    if start != total:
        raise PipelineError(f"{path}: wrote {start} points where {total} were planned")
    group.attrs.update({
        "crs_wkt": meta.crs_wkt, "sources": meta.sources, "ratio": meta.ratio, "method": meta.method,
        "software_version": meta.version, "las_version": str(header.version), "point_format": point_format.id,
        "scales": [float(s) for s in header.scales], "offsets": [float(o) for o in header.offsets],
        "tile_index": tile_index, "provenance": run_record(meta),
    })
    return start
