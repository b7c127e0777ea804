"""The zarr output, an xarray-native dataset: the kept points along `point` (x, y, z as its coordinates, every
other LAS dimension a data variable, CF attributes on each), the CRS as the grid-mapping variable
`spatial_ref`, and the tile index as arrays along `tile`, so a reader can load one area without all.

Format: zarr v2 with consolidated metadata (`.zmetadata`), because it is the one layout every reader opens
without a warning. Without consolidation xarray 2026.9 warns on each `open_zarr` ("Failed to open Zarr store
with consolidated metadata"); consolidating a v3 store makes zarr 3.1.6 warn that consolidated metadata is
not part of the v3 specification and "may not be supported by other zarr implementations"; and GDAL 3.10
(rasterio 1.4.4's) cannot read zarr-python's v3 arrays at all ("Unsupported codec: bytes") while it reads
these. Arrays carry no fill value: xarray would read a v2 fill value as missing data and turn integers into
floats.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Iterable, Sequence

import laspy
import numpy as np
import pyproj
import zarr

from pipeline.errors import PipelineError
from pipeline.io.crs import crs_from_wkt
from pipeline.io.extra_bytes import described_point_format
from pipeline.io.output_meta import OutputMeta
from pipeline.io.provenance import run_record
from pipeline.io.zarr_attrs import (COORDINATES, GRID_MAPPING, TILE_BOUNDS, TILE_COLUMNS, grid_mapping_attrs,
                                    point_attrs, tile_attrs)
from tiling.assemble import TilePart

ZARR_CHUNK = 1_000_000
ZARR_FORMAT = 2


RESERVED = (GRID_MAPPING, "point", "tile", *TILE_COLUMNS)  # the writer's own array and dimension names, beside x, y, z
EXTRA_PREFIX = "extra_"  # put before a LAS dimension name that clashes with one of them


def zarr_dimensions(point_format: laspy.PointFormat) -> dict[str, str]:
    """The array names of a zarr output, each mapped to the LAS dimension it holds: scaled x, y, z, then every
    other LAS dimension (extra bytes too) under its own name where safe, else a unique one (see `safe_variable`),
    so no dimension is lost or overwritten."""
    taken = {name.casefold() for name in (*COORDINATES, *RESERVED)}
    variables = {name: name for name in COORDINATES}
    for name in point_format.dimension_names:
        if name not in ("X", "Y", "Z"):
            variables[safe_variable(name, taken, point_format.dimension_by_name(name).num_elements > 1)] = name
    return variables


def safe_variable(name: str, taken: set[str], elements: bool) -> str:
    """An array name for the LAS dimension `name`, not in `taken` and added to it (casefolded: on a case-blind
    disk a store's arrays are folders that would clash). `/` and `\\` become `_`, since zarr would make a nested
    group that xarray never shows; a clashing name or a zarr key (`.zarray`, `..`) gets `EXTRA_PREFIX` until
    unique, and so does one whose `<name>_element` dimension (with `elements`) would clash."""
    safe = name.replace("/", "_").replace("\\", "_")
    if not safe or safe.startswith("."):
        safe = EXTRA_PREFIX + safe

    def keys(candidate: str) -> set[str]:
        """The casefolded names the candidate uses: its own, and its element dimension's."""
        return {candidate.casefold(), *([f"{candidate}_element".casefold()] if elements else [])}

    while keys(safe) & taken:
        safe = EXTRA_PREFIX + safe
    taken.update(keys(safe))
    return safe


def write_zarr(path: Path, header: laspy.LasHeader, total: int, parts: Iterable[TilePart], meta: OutputMeta) -> int:
    """Stream the parts into one (total,) array per dimension ((total, k) for an extra-bytes array), whole chunks
    at a time (memory bounded by about a chunk, not the output), then write the tile index, the CRS and the run's
    attributes; return the points."""
    group = zarr.open_group(str(path), mode="w", zarr_format=ZARR_FORMAT)
    crs = crs_from_wkt(meta.crs_wkt)
    header = described_header(header)  # every extra-bytes field by its own name, not laspy's `ExtraBytes` run
    point_format = header.point_format
    names = zarr_dimensions(point_format)  # array name -> LAS name, which the attributes keep (las_dimension)
    probe = laspy.ScaleAwarePointRecord.zeros(1, header=header)
    mapping = {"grid_mapping": GRID_MAPPING} if crs is not None else {}  # only a CRS pyproj reads: readers parse it
    links = {"coordinates": " ".join([*COORDINATES, *mapping.values()]), **mapping}  # a data variable's coords
    chunk = min(ZARR_CHUNK, max(total, 1))
    arrays = {}
    for variable, name in names.items():
        sample = np.asarray(probe[name])  # (1,), or (1, k) for an extra-bytes array of k elements
        dims = ("point", *(f"{variable}_element" for _ in sample.shape[1:]))
        attrs = point_attrs(name, header, crs) | _data_links(variable, links)
        arrays[variable] = _variable(group, variable, dims, attrs, dtype=sample.dtype, shape=(total, *sample.shape[1:]),
                                     chunks=(chunk, *sample.shape[1:]))
    tile_ids: list[int] = []
    tile_bounds: list[tuple[float, float, float, float]] = []
    tile_counts: list[int] = []
    start, written, pending = 0, 0, []

    def flush(final: bool) -> int:
        """Write whole chunks of the pending records (all of them when final); return the new write position."""
        records = np.concatenate(pending).view(point_format.dtype()) if pending else np.empty(0, point_format.dtype())
        size = len(records) if final else len(records) // ZARR_CHUNK * ZARR_CHUNK
        record = laspy.ScaleAwarePointRecord(records[:size], point_format, header.scales, header.offsets)
        for variable, name in names.items():
            arrays[variable][written:written + size] = np.asarray(record[name])
        pending[:] = [records[size:]]
        return written + size

    for part in parts:
        tile_ids.append(part.tile_id)
        tile_bounds.append(part.bounds)
        tile_counts.append(len(part.records))
        start += len(part.records)
        pending.append(part.records)
        if start - written >= ZARR_CHUNK:
            written = flush(final=False)
    written = flush(final=True)
    if start != total:
        raise PipelineError(f"{path}: wrote {start} points where {total} were planned")
    _write_tile_index(group, tile_ids, tile_bounds, tile_counts, crs, mapping)
    if crs is not None:
        _variable(group, GRID_MAPPING, (), grid_mapping_attrs(crs), data=np.array(0, dtype=np.int32))
    group.attrs.update({
        "crs_wkt": meta.crs_wkt, "sources": meta.sources, "ratio": meta.ratio, "method": meta.method,
        "software_version": meta.version, "las_version": str(header.version), "point_format": point_format.id,
        "scales": [float(s) for s in header.scales], "offsets": [float(o) for o in header.offsets],
        "provenance": run_record(meta), "coordinates": " ".join(TILE_COLUMNS),  # coords along tile, for xarray
    })
    zarr.consolidate_metadata(str(path))
    return start


def described_header(header: laspy.LasHeader) -> laspy.LasHeader:
    """A copy of `header` whose point format names its extra bytes as all its extra-bytes VLRs do
    (pipeline.io.extra_bytes); the same record layout, so records are viewed in its dtype."""
    described = described_point_format(header)
    if described is header.point_format:
        return header
    copy = laspy.LasHeader(version=header.version, point_format=described)
    copy.scales, copy.offsets, copy.global_encoding = header.scales, header.offsets, header.global_encoding
    return copy


def _write_tile_index(group: zarr.Group, ids: Sequence[int], bounds: Sequence[tuple[float, float, float, float]],
                      counts: Sequence[int], crs: pyproj.CRS | None, mapping: dict[str, str]) -> None:
    """The tile index as (tiles,) arrays along `tile`: the id (its index), XY bounds, and the start and count of
    its points along `point` (tiles are written contiguously, in this order). xarray reads them as coordinates
    (the group's `coordinates` attribute names them), so `Dataset.where` never broadcasts them against points."""
    count = np.asarray(counts, dtype=np.int64)
    box = np.asarray(bounds, dtype=np.float64).reshape(-1, 4)
    columns = {"tile": np.asarray(ids, dtype=np.int64), **{name: box[:, i] for i, name in enumerate(TILE_BOUNDS)},
               "tile_start": np.cumsum(count) - count, "tile_count": count}
    for name, values in columns.items():
        _variable(group, name, ("tile",), tile_attrs(name, crs) | (mapping if name in TILE_BOUNDS else {}), data=values)


def _variable(group: zarr.Group, name: str, dims: tuple[str, ...], attrs: dict[str, Any], **array: Any) -> zarr.Array:
    """A zarr array along `dims` (named for xarray by `_ARRAY_DIMENSIONS`) with `attrs` and no fill value;
    `array` is zarr's shape, dtype and chunks, or data."""
    return group.create_array(name, fill_value=None, attributes={"_ARRAY_DIMENSIONS": list(dims), **attrs}, **array)


def _data_links(name: str, links: dict[str, str]) -> dict[str, str]:
    """The links (coordinates, grid_mapping) of a point variable: none on x, y, z, which are coordinates."""
    return {} if name in COORDINATES else links
