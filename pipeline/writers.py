"""Output writers: LAS/LAZ with the input's header, or a zarr v3 group of one array per dimension."""
from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import laspy
import numpy as np
import zarr

from pipeline.atomic import atomic_output
from pipeline.errors import PipelineError, file_system_error

OUTPUT_SUFFIXES = (".las", ".laz", ".zarr")
ZARR_CHUNK = 1_000_000


@dataclass(frozen=True)
class TilePart:
    """One tile's kept points, in output order, and their XY bounds (the core rectangle, grown to hold them)."""

    tile_id: int
    bounds: tuple[float, float, float, float]
    records: np.ndarray


@dataclass
class OutputMeta:
    """What the zarr store records about the run besides the points."""

    crs_wkt: str | None
    sources: list[str]
    ratio: float
    method: str
    version: str


def write_output(path: Path, header: laspy.LasHeader, total: int, parts: Iterable[TilePart], meta: OutputMeta) -> int:
    """Write the parts to path (by suffix) through a temporary name; return the points written.

    A write that fails (a full disk) leaves nothing under either name and is reported against `path`.
    """
    suffix = path.suffix.lower()
    if suffix not in OUTPUT_SUFFIXES:
        raise PipelineError(f"{path}: unsupported output type {suffix or '(none)'} (use .las, .laz or .zarr)")
    try:
        with atomic_output(path) as temporary:
            if suffix == ".zarr":
                written = _write_zarr(temporary, header, total, parts, meta)
            else:
                written = _write_las(temporary, header, parts, compress=suffix == ".laz")
    except OSError as exc:
        raise file_system_error(exc, path) from None
    return written


class RecordingFile(io.FileIO):
    """A file opened for writing that keeps the OSError of a failed write (a full disk): lazrs reports
    one only as 'IoError: Failed to call write', which names neither the cause nor the file."""

    def __init__(self, path: Path) -> None:
        super().__init__(path, "w")
        self.error: OSError | None = None

    def write(self, data: bytes) -> int:  # type: ignore[override]
        try:
            return super().write(data)
        except OSError as exc:
            self.error = exc
            raise


def _write_las(path: Path, header: laspy.LasHeader, parts: Iterable[TilePart], compress: bool) -> int:
    """Stream the parts into a LAS/LAZ file, then the input's EVLRs; laspy fills in count and bounds on close."""
    written = 0
    evlrs = header.evlrs
    raw = RecordingFile(path)
    try:
        with io.BufferedWriter(raw) as stream, \
                laspy.open(stream, mode="w", header=header, do_compress=compress, closefd=False) as writer:
            for part in parts:
                writer.write_points(laspy.PackedPointRecord(part.records, header.point_format))
                written += len(part.records)
            if evlrs:
                writer.write_evlrs(evlrs)
    except Exception:
        if raw.error is not None:
            raise raw.error from None
        raise
    return written


def zarr_dimensions(point_format: laspy.PointFormat) -> list[str]:
    """Array names of a zarr output: scaled x, y, z, then every other LAS dimension (extra bytes too)."""
    return ["x", "y", "z"] + [n for n in point_format.dimension_names if n not in ("X", "Y", "Z")]


def _write_zarr(path: Path, header: laspy.LasHeader, total: int, parts: Iterable[TilePart], meta: OutputMeta) -> int:
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
        "tile_index": tile_index,
    })
    return start
