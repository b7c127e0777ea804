"""The COPC 1.0 output (`-o X.copc.laz`): a LAZ 1.4 file whose points are stored one LAZ chunk per octree
node, so a viewer can read an area or a level of detail without reading the rest.

Levels are the prefix of our priority order. Within a tile the simplifier returns points most important
first (an FPS-like progressive order), so a point's global priority is its fractional position in its tile,
f = (i + 0.5) / n, and the first k % of every tile is the scan's best k % simplification. Level l holds the
points with C[l-1] <= f < C[l], where C[l] = (4^(l+1) - 1) / (4^(D+1) - 1) is the cumulative share of levels
0..l: each level holds 4x the points of the one above (LiDAR lies on surfaces, so a level's nodes are about
4x as many, not 8x), and the depth D is the smallest for which the root holds at most NODE_POINTS points
(so nodes hold about that many points each; on a narrow corridor cells fill 2 of 8 children, and the
deepest nodes hold more: 375k points at level 3 of a 4M-point street). Within a level, a point goes to the
node whose cube holds it; within a node, points keep the output order (tile by tile, priority order within).

Streaming in bounded memory: a first pass spills each level's records to a scratch file beside the output
(counting bounds, GPS time range and returns); a second pass splits each level into its nodes, a few octree
levels at a time, until a part fits in LOAD_POINTS records or is one node, and compresses node by node. Peak
memory is the largest node (or LOAD_POINTS records) plus fixed buffers, never the whole output.

Library: written here with lazrs (laspy's LAZ backend: one LAZ chunk per node, variable-size chunk table)
and laspy (header, VLRs, EVLRs). copclib 2.6.3 was measured on the same nodes (200k points: 1.06 M points/s
against 1.15 M here, identical point records) but fails checks: its writer keeps no VLR but WKT and extra
bytes (provenance and the input's EVLRs are lost), leaves header bounds, returns, spacing and GPS range at 0
unless set by hand, and its reader misreads a WKT VLR (as PDAL writes it) by 6 bytes. It stays as the tests'
second, independent reader.
"""
from __future__ import annotations

import io
import os
import shutil
import struct
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO, Iterable, Iterator

import laspy
import lazrs
import numpy as np
from laspy.vlrs.known import ExtraBytesVlr, WktCoordinateSystemVlr
from laspy.vlrs.vlrlist import VLRList

from pipeline.errors import PipelineError
from pipeline.io.crs import las_wkt
from pipeline.io.extra_bytes import described_point_format
from pipeline.io.output_meta import OutputMeta, priority_fraction
from tiling.assemble import TilePart

COPC_FORMATS = {0: 6, 1: 6, 2: 7, 3: 7, 6: 6, 7: 7, 8: 8}  # input point format -> the COPC one that holds it
NODE_POINTS = 60_000        # points the root holds at most; other nodes hold about as many on surface data
LEVEL_GROWTH = 4            # points per level grow 4x: surfaces fill 4 of a cube's 8 children
LOAD_POINTS = 250_000       # records read at once while splitting a level into its nodes
SPLIT_LEVELS = 2            # octree levels one split pass descends (at most 8^2 scratch files open)
SCAN_ANGLE_UNIT = 0.006     # degrees per unit of the LAS 1.4 scan_angle field
INFO_SIZE = 160             # bytes of the COPC info VLR's record
EVLR_HEADER_SIZE = 60
KEY_BITS = 21               # bits of a cell key per axis when packed in one int64
ENTRY = struct.Struct("<iiiiQii")  # hierarchy entry: key (level, x, y, z), offset, byte size, point count
COPC_USER_ID = "copc"
GEOTIFF_RECORDS = (34735, 34736, 34737)  # LASF_Projection's GeoTIFF keys, doubles and strings
WKT_RECORD_ID = 2112
WKT_USER_IDS = ("LASF_Projection", "liblas")  # libLAS (and PDAL) write a copy of the WKT record as `liblas`
COPC_SPILL_COPIES = 2       # the spill beside the output holds the kept records about twice at its peak (a level
                            # and its split parts), uncompressed


def write_copc(path: Path, header: laspy.LasHeader, total: int, parts: Iterable[TilePart], meta: OutputMeta) -> int:
    """Write the parts as a COPC 1.0 file at `path` (header already stamped); return the points written.

    Scratch files live in a folder beside `path`, removed on success and on failure; its name ends in
    `-<pid>` as `path`'s does, so pipeline.io.atomic's clean-up of a killed run's leftovers removes it too.
    """
    point_format = copc_point_format(described_point_format(header))
    scratch = path.parent / f"{path.name}-{os.getpid()}"
    scratch.mkdir()
    try:
        spill = LevelSpill(scratch, level_bounds(total), point_format)
        for part in parts:
            spill.add(to_copc_records(part.records, header.point_format, point_format))
        spill.close()
        if spill.written != total:
            raise PipelineError(f"{path}: wrote {spill.written} points where {total} were planned")
        with open(path, "wb") as stream:
            write_file(stream, copc_header(header, point_format, meta), spill)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    return spill.written


def copc_point_format(source: laspy.PointFormat) -> laspy.PointFormat:
    """The COPC point format (6, 7 or 8) holding every field of `source`, with its extra bytes."""
    if source.id not in COPC_FORMATS:
        raise PipelineError(f"point format {source.id} carries waveform packets, which COPC 1.0 (formats 6-8) "
                            "cannot hold: write .laz to keep them")
    target = laspy.PointFormat(COPC_FORMATS[source.id])
    for dimension in source.extra_dimensions:
        names = byte_fields(dimension)
        if not names:
            target.dimensions.append(dimension)
        for index, name in enumerate(names):
            target.add_extra_dimension(laspy.ExtraBytesParams(name, "u1", f"byte {index} of {dimension.name}"[:32]))
    return target


def byte_fields(dimension: laspy.DimensionInfo) -> list[str]:
    """The names of the one-byte fields (`<name>_<i>`) that hold `dimension` in COPC when it is a run of bytes
    (the input's undocumented extra bytes, which laspy reads as one `ExtraBytes` field), else []: laspy describes
    a run of more than 3 as data_type 0 with options = its byte count, then reads those options back as
    scale/offset flags and cannot open the file, and one of 2 or 3 by an array type (11-30), which LAS 1.4 R15
    deprecates and copc.js rejects; one `u1` field per byte round-trips and keeps every byte."""
    dtype = dimension.dtype
    if dimension.is_standard or dtype is None or dtype.base != np.uint8 or dimension.num_elements <= 1:
        return []
    return [f"{dimension.name}_{index}" for index in range(dimension.num_elements)]


def to_copc_records(records: np.ndarray, source: laspy.PointFormat, target: laspy.PointFormat) -> np.ndarray:
    """(n,) records of `source` as records of `target`: fields copied by name as laspy's conversion does, the extra
    bytes as they are (`target` names them as the VLRs do and splits byte runs, see `copc_point_format`), and the
    legacy scan_angle_rank (degrees) converted to scan_angle (0.006 degree units), which laspy leaves 0."""
    if source.id == target.id:  # the extra bytes keep their layout under their new names: same records
        return records if records.dtype == target.dtype() else records.view(target.dtype())
    packed = laspy.PackedPointRecord(records, source)
    converted = laspy.PackedPointRecord.from_point_record(packed, target)
    converted["scan_angle"] = np.rint(np.asarray(packed["scan_angle_rank"]) / SCAN_ANGLE_UNIT).astype(np.int16)
    if extra := source.num_extra_bytes:
        record_bytes(converted.array)[:, -extra:] = record_bytes(records)[:, -extra:]
    return converted.array


def record_bytes(records: np.ndarray) -> np.ndarray:
    """(n, record size) uint8 bytes of (n,) records: a view of contiguous records, which writes through."""
    return np.ascontiguousarray(records).view(np.uint8).reshape(len(records), records.dtype.itemsize)


def level_bounds(total: int) -> np.ndarray:
    """(depth + 1,) cumulative priority share C[l] of levels 0..l for `total` points (see the module docstring)."""
    sizes = [1]
    while total * sizes[0] > NODE_POINTS * sum(sizes):
        sizes.append(sizes[-1] * LEVEL_GROWTH)
    cumulative = np.cumsum(sizes, dtype=np.float64)
    return cumulative / cumulative[-1]


def priority_levels(count: int, bounds: np.ndarray) -> np.ndarray:
    """(count + 1,) start of each level's run of a tile's `count` records in priority order, then `count`."""
    return np.concatenate([[0], np.searchsorted(priority_fraction(count), bounds[:-1], side="left"), [count]])


class LevelSpill:
    """Pass one: each level's records appended to its own scratch file, with the totals the header needs."""

    def __init__(self, folder: Path, bounds: np.ndarray, point_format: laspy.PointFormat) -> None:
        self.bounds, self.dtype = bounds, point_format.dtype()
        self.paths = [folder / f"level-{level}" for level in range(len(bounds))]
        self._files = ExitStack()
        self.streams = [self._files.enter_context(open(p, "wb")) for p in self.paths]
        self.counts = np.zeros(len(bounds), dtype=np.int64)
        self.mins = np.full(3, np.iinfo(np.int64).max)
        self.maxs = np.full(3, np.iinfo(np.int64).min)
        self.gps = (np.inf, -np.inf)
        self.returns = np.zeros(16, dtype=np.int64)  # points by return number 0..15

    @property
    def written(self) -> int:
        return int(self.counts.sum())

    def add(self, records: np.ndarray) -> None:
        """Spill one tile's records (priority order), split into their levels."""
        starts = priority_levels(len(records), self.bounds)
        for level, (lo, hi) in enumerate(zip(starts[:-1], starts[1:])):
            self.streams[level].write(records[lo:hi].tobytes())  # not tofile: its errors lose errno (ENOSPC)
            self.counts[level] += hi - lo
        if len(records) == 0:
            return
        ints = np.column_stack([records["X"], records["Y"], records["Z"]])
        self.mins, self.maxs = np.minimum(self.mins, ints.min(0)), np.maximum(self.maxs, ints.max(0))
        times = records["gps_time"]
        self.gps = (min(self.gps[0], float(times.min())), max(self.gps[1], float(times.max())))
        self.returns += np.bincount(records["bit_fields"] & 0x0F, minlength=16)

    def close(self) -> None:
        self._files.close()


@dataclass(frozen=True)
class Cube:
    """The octree's root cube, in scaled coordinates: center (3,) and half its edge."""

    center: np.ndarray
    halfsize: float

    @classmethod
    def on(cls, mins: np.ndarray, maxs: np.ndarray, step: float) -> "Cube":
        """The cube whose minimum corner is the box's and whose edge is its longest side (`step` for a single
        point), as PDAL's untwine writes it: readers such as copclib take the header's minimum as the cube's.
        Readers compute the cube in float64, which rounds (autzen_trim: centre - halfsize is 636006.3900000001
        for a minimum of 636006.39, so boundary points fell outside it), so the centre is lowered and the halfsize
        raised by a coordinate's rounding step at a time until the cube holds the box both ways readers compute
        it: centre -+ halfsize (copc.js, copc-validator), and that minimum plus the edge taken from x (laspy, see
        `cells`). Not widened by a scale step: copclib's cells start at the header's minimum, and cells shifted
        by a step would put points near their faces in nodes copclib says do not hold them."""
        halfsize = max(float((maxs - mins).max()), step) / 2
        center = mins + halfsize
        rounding = float(np.spacing(np.abs(np.concatenate([mins, maxs])).max()))
        while True:
            low = center - halfsize
            if np.any(low > mins):
                center = np.where(low > mins, np.nextafter(center, -np.inf), center)
            elif np.any(center + halfsize < maxs) or np.any(low + ((center[0] + halfsize) - low[0]) < maxs):
                halfsize += rounding
            else:
                return cls(center, halfsize)

    def cells(self, records: np.ndarray, header: laspy.LasHeader, level: int) -> np.ndarray:
        """(n,) packed cell (see `pack`) of each record at `level`, exact against the cell bounds readers
        compute (laspy: cube minimum + key * edge, the edge taken from x); a point on a face may go either way."""
        low = self.center - self.halfsize
        edge = ((self.center[0] + self.halfsize) - low[0]) / 2 ** level
        last = 2 ** level - 1
        keys = []
        for axis, name in enumerate("XYZ"):
            at = records[name] * header.scales[axis] + header.offsets[axis]
            key = np.clip(np.floor((at - low[axis]) / edge), 0, last).astype(np.int64)
            key -= (at < low[axis] + key * edge) & (key > 0)
            key += (at > low[axis] + (key + 1) * edge) & (key < last)
            keys.append(key)
        return pack(*keys)


def pack(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
    """(n,) int64 x << 42 | y << 21 | z of (n,) cell keys (21 bits each: levels up to 21)."""
    return (x << 2 * KEY_BITS) | (y << KEY_BITS) | z


def unpack(cell: int) -> tuple[int, int, int]:
    """The x, y, z of one packed cell."""
    mask = (1 << KEY_BITS) - 1
    return cell >> 2 * KEY_BITS, (cell >> KEY_BITS) & mask, cell & mask


def ancestors(cells: np.ndarray, up: int) -> np.ndarray:
    """(n,) packed cells `up` levels above (n,) packed cells, so a point's node lies inside its ancestors'."""
    mask = (1 << KEY_BITS) - 1
    return pack((cells >> 2 * KEY_BITS) >> up, ((cells >> KEY_BITS) & mask) >> up, (cells & mask) >> up)


def runs(values: np.ndarray) -> Iterator[tuple[int, np.ndarray]]:
    """Each distinct value of (n,) `values` with the indices holding it, in value order, stable within."""
    order = np.argsort(values, kind="stable")
    starts = np.flatnonzero(np.diff(values[order], prepend=-1))
    for lo, hi in zip(starts, np.append(starts[1:], len(order))):
        yield int(values[order[lo]]), order[lo:hi]


def node_records(path: Path, count: int, depth: int, level: int, cube: Cube, header: laspy.LasHeader,
                 dtype: np.dtype) -> Iterator[tuple[tuple[int, int, int, int], np.ndarray]]:
    """The nodes of one level, as (key, (n,) records in file order), from a scratch file of `count` records
    that all lie in one cell at `depth`: read whole when small or one node, else split SPLIT_LEVELS levels
    down into child files first; every file is deleted once read."""
    if depth == level or count <= LOAD_POINTS:
        records = np.fromfile(path, dtype=dtype)
        path.unlink()
        for cell, picked in runs(cube.cells(records, header, level)):
            yield (level, *unpack(cell)), records[picked]
        return
    below = min(level, depth + SPLIT_LEVELS)
    children: dict[int, tuple[Path, int]] = {}
    with ExitStack() as files, open(path, "rb") as source:
        streams: dict[int, BinaryIO] = {}
        while len(chunk := np.fromfile(source, dtype=dtype, count=LOAD_POINTS)):
            for cell, picked in runs(ancestors(cube.cells(chunk, header, level), level - below)):
                if cell not in streams:
                    child = path.parent / f"{path.name}-{below}-{cell}"
                    streams[cell] = files.enter_context(open(child, "wb"))
                    children[cell] = (child, 0)
                streams[cell].write(chunk[picked].tobytes())
                children[cell] = (children[cell][0], children[cell][1] + len(picked))
    path.unlink()
    for child, size in children.values():
        yield from node_records(child, size, below, level, cube, header, dtype)


def compress_node(records: np.ndarray, laszip: lazrs.LazVlr) -> bytes:
    """One node's records as one LAZ chunk (a chunk decodes on its own, so one compressor per node)."""
    buffer = io.BytesIO()
    compressor = lazrs.LasZipCompressor(buffer, laszip)
    compressor.compress_many(records.view(np.uint8).ravel())
    compressor.finish_current_chunk()
    return buffer.getvalue()[8:]  # the compressor first reserves 8 bytes for the chunk table's offset


def hierarchy_page(entries: dict[tuple[int, int, int, int], tuple[int, int, int]]) -> bytes:
    """The one hierarchy page: an entry (offset, bytes, points) per node, plus an empty entry for every
    ancestor of a node that holds no points itself (readers walk down from the root)."""
    keys = set(entries)
    for level, x, y, z in list(keys):
        while level > 0:
            level, x, y, z = level - 1, x >> 1, y >> 1, z >> 1
            keys.add((level, x, y, z))
    return b"".join(ENTRY.pack(*key, *entries.get(key, (0, 0, 0))) for key in sorted(keys))


def copc_header(header: laspy.LasHeader, point_format: laspy.PointFormat, meta: OutputMeta) -> laspy.LasHeader:
    """A LAS 1.4 header in the COPC format for the input's (stamped) header: its identity fields, scales and
    offsets, and its VLRs and EVLRs after a COPC info placeholder and the run's CRS as one WKT1 record (see
    `without_crs`); laspy makes one extra-bytes VLR from the point format's extra dimensions (see `clear_min_max`)."""
    copc = laspy.LasHeader(version="1.4", point_format=point_format)
    for field in ("file_source_id", "uuid", "system_identifier", "generating_software", "creation_date"):
        setattr(copc, field, getattr(header, field))
    copc.scales = np.asarray(header.scales, dtype=np.float64)
    copc.offsets = np.asarray(header.offsets, dtype=np.float64)
    copc.global_encoding.gps_time_type = header.global_encoding.gps_time_type
    copc.global_encoding.wkt = True
    wkt = [WktCoordinateSystemVlr(las_wkt(meta.crs_wkt))] if meta.crs_wkt else []
    kept = without_crs([v for v in header.vlrs if v.user_id not in (COPC_USER_ID, "laszip encoded")], bool(wkt))
    copc.vlrs = VLRList([laspy.VLR(COPC_USER_ID, 1, "COPC info VLR", bytes(INFO_SIZE)), *wkt, *kept])
    clear_min_max(copc.vlrs)
    copc.evlrs = VLRList(without_crs([v for v in header.evlrs or [] if v.user_id != COPC_USER_ID], bool(wkt)))
    return copc


def without_crs(records: list[laspy.VLR], wkt_written: bool) -> list[laspy.VLR]:
    """The input's (E)VLRs less the CRS records the COPC file's one WKT record replaces, so every reader finds the
    same CRS: the GeoTIFF keys (LAS 1.4 formats 6-8 with the WKT bit describe the CRS in WKT only) and, where a
    WKT record is written, every input WKT record (`LASF_Projection`'s, and libLAS's copy under `liblas`)."""
    return [v for v in records if not (v.user_id == "LASF_Projection" and v.record_id in GEOTIFF_RECORDS
                                       or wkt_written and v.user_id in WKT_USER_IDS and v.record_id == WKT_RECORD_ID)]


def clear_min_max(vlrs: Iterable[laspy.VLR]) -> None:
    """Mark the min and max of every typed extra-bytes field as absent, and zero them: laspy marks both and fills
    them in as it writes points, which this writer does node by node without it, so they would keep laspy's
    placeholders (min 2^64-1 and max 0 for integers, +-1.8e308 for floats), which readers take as values (copc.js
    cannot open the file: "Cannot convert bigint to number"). Untyped bytes (data type 0) count bytes in options."""
    for vlr in vlrs:
        for field in vlr.extra_bytes_structs if isinstance(vlr, ExtraBytesVlr) else ():
            if field.data_type:
                field.options &= ~(field.MIN_BIT_MASK | field.MAX_BIT_MASK)
                field._min, field._max = type(field._min)(), type(field._max)()


def info_record(cube: Cube, spacing: float, hierarchy: tuple[int, int], gps: tuple[float, float]) -> bytes:
    """The COPC info VLR's 160 bytes: cube, root spacing, root hierarchy page (offset, size), GPS time range."""
    return struct.pack("<5d2Q2d", *cube.center, cube.halfsize, spacing, *hierarchy, *gps) + bytes(88)


def write_file(stream: BinaryIO, header: laspy.LasHeader, spill: LevelSpill) -> None:
    """Pass two: header and VLRs (placeholders), every node's chunk level by level, the chunk table, the
    hierarchy and the input's EVLRs; then the header and VLRs again with the final counts and offsets."""
    laszip = lazrs.LazVlr.new_for_compression(header.point_format.id, header.point_format.num_extra_bytes, True)
    header.vlrs.append(laspy.vlrs.known.LasZipVlr(laszip.record_data()))
    header.are_points_compressed = True
    header.write_to(stream)
    table_offset = stream.tell()
    stream.write(bytes(8))
    empty = spill.written == 0
    mins = (np.zeros(3) if empty else spill.mins) * header.scales + header.offsets
    maxs = (np.zeros(3) if empty else spill.maxs) * header.scales + header.offsets
    cube = Cube.on(mins, maxs, float(header.scales.max()))
    entries, chunks = {}, []
    for level, path in enumerate(spill.paths):
        for key, records in node_records(path, int(spill.counts[level]), 0, level, cube, header, spill.dtype):
            chunk = compress_node(records, laszip)
            entries[key] = (stream.tell(), len(chunk), len(records))
            chunks.append((len(records), len(chunk)))
            stream.write(chunk)
    table_position = stream.tell()
    lazrs.write_chunk_table(stream, chunks, laszip)
    evlr_start = stream.tell()
    page = hierarchy_page(entries)
    evlrs = VLRList([laspy.VLR(COPC_USER_ID, 1000, "EPT hierarchy", page)] + list(header.evlrs))
    evlrs.write_to(stream, as_extended=True)
    stream.seek(table_offset)
    stream.write(struct.pack("<q", table_position))
    root = max(int(spill.counts[0]), 1)
    spacing = 2 * cube.halfsize / np.sqrt(root)  # root points spread over the cube's face
    header.vlrs[0].record_data = info_record(cube, spacing, (evlr_start + EVLR_HEADER_SIZE, len(page)),
                                             spill.gps if not empty else (0.0, 0.0))
    header.point_count = spill.written
    header.mins, header.maxs = mins, maxs
    header.number_of_points_by_return = spill.returns[1:16].astype(np.uint64)
    header.start_of_first_evlr, header.number_of_evlrs = evlr_start, len(evlrs)
    stream.seek(0)
    header.write_to(stream, ensure_same_size=True)
