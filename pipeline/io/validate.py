"""Input checks that fail fast with one line naming the file: paths, LAS headers and decoded points.

Everything the tile grid relies on in a file is checked here: finite scale/offset/bounds, a point count the
data can hold, and points inside the header's bounds. What a run needs beyond its files (one CRS in metres,
disk room) is checked in pipeline.engine.preflight.
"""
from __future__ import annotations

from pathlib import Path
from typing import BinaryIO

import laspy
import numpy as np

from model.rules import column_max, column_min
from pipeline.errors import PipelineError

LAS_PREAMBLE_BYTES = 104  # the LAS header up to and including its VLR count
VERSION_OFFSET = 24        # major, then minor
VLR_COUNT_OFFSET = 100
VLR_HEADER_BYTES = 54     # the fixed part of every VLR
VLR_LENGTH_AT = 20        # its record length after the header: after reserved (2), user id (16), record id (2)
HEADER_SIZE_AT, POINT_OFFSET_AT = 94, 96
MIN_HEADER_BYTES = 227    # LAS 1.0-1.2; 1.3 adds 8 bytes, 1.4 another 140
LAS14_HEADER_BYTES = 375
EVLR_START_AT, EVLR_COUNT_AT = 235, 243
EVLR_HEADER_BYTES = 60
LEGACY_COUNT_AT, POINT_COUNT_14_AT = 107, 247
LASZIP_USER, LASZIP_CHUNK_SIZE_AT = b"laszip encoded", 12  # chunk size: after compressor, coder, version, options
VARIABLE_CHUNKS = 0xFFFFFFFF  # laszip's chunk size when each chunk has its own point count (COPC writes these)
CHUNK_TABLE_HEADER_BYTES = 8  # version, number of chunks
BOUNDS_SLACK_STEPS = 100  # points may stray this many grid steps (scale) outside the header's bounds ...
BOUNDS_SLACK_SHARE = 0.01  # ... or this share of its extent, whichever is larger


def check_input_path(path: Path) -> None:
    """The input exists and is a regular file (not a folder, a device or a missing name)."""
    if path.is_dir() and path.suffix.lower() == ".zarr":
        raise PipelineError(f"{path}: is a zarr store, which this command does not read (it reads LAS/LAZ/COPC/PLY "
                            "files; `pipeline eval` scores a store against its source)")
    if path.is_dir():
        raise PipelineError(f"{path}: is a folder, not a point cloud file (pass the files in it, e.g. {path}/*.laz)")
    if not path.exists():
        raise PipelineError(f"{path}: no such file")
    if not path.is_file():
        raise PipelineError(f"{path}: not a regular file")


def check_las_preamble(path: Path, head: bytes, file_size: int) -> None:
    """The LASF signature, a LAS version laspy reads and writes, and a VLR count the file can hold:
    laspy reads that many VLRs without looking for the end of the file, so a corrupt count keeps it busy for hours."""
    if head[:4] != b"LASF":
        raise PipelineError(f"{path}: not a LAS/LAZ file (it does not start with the LASF signature)")
    if len(head) < LAS_PREAMBLE_BYTES:
        raise PipelineError(f"{path}: LAS header cut short ({file_size} bytes; truncated file?)")
    major, minor = head[VERSION_OFFSET], head[VERSION_OFFSET + 1]
    if major != 1 or minor > 4:
        raise PipelineError(f"{path}: LAS version {major}.{minor} is not one of 1.0 to 1.4 (corrupt header?)")
    vlr_count = int.from_bytes(head[VLR_COUNT_OFFSET:VLR_COUNT_OFFSET + 4], "little")
    if vlr_count * VLR_HEADER_BYTES > file_size:
        raise PipelineError(f"{path}: header declares {vlr_count:,} VLRs, more than a {file_size:,}-byte file "
                            "holds (corrupt header)")


def check_las_layout(path: Path, stream: BinaryIO, file_size: int) -> None:
    """The header's layout adds up before laspy trusts it: its size, the VLRs it declares ending at or before
    the point data's start (else points would be read from VLR bytes: garbage, exit 0), the point data
    starting inside the file, LAS 1.4 EVLRs after the points and within the file (else laspy loops
    over billions of them), and a LAZ chunk table with a believable chunk count."""
    stream.seek(0)
    head = stream.read(LAS14_HEADER_BYTES)
    header_size, point_offset = field(head, HEADER_SIZE_AT, 2), field(head, POINT_OFFSET_AT, 4)
    if not MIN_HEADER_BYTES <= header_size <= point_offset:
        raise PipelineError(f"{path}: header size {header_size} does not fit before the point data at byte "
                            f"{point_offset} (corrupt header)")
    if point_offset > file_size:
        raise PipelineError(f"{path}: point data said to start at byte {point_offset:,}, past the end of a "
                            f"{file_size:,}-byte file (corrupt header or truncated file)")
    chunk_size = laszip_chunk_size(path, stream, header_size, field(head, VLR_COUNT_OFFSET, 4), point_offset)
    minor = head[VERSION_OFFSET + 1]
    if minor >= 4 and len(head) >= EVLR_COUNT_AT + 4:
        evlr_start, evlr_count = field(head, EVLR_START_AT, 8), field(head, EVLR_COUNT_AT, 4)
        if evlr_count and not point_offset <= evlr_start <= file_size - evlr_count * EVLR_HEADER_BYTES:
            raise PipelineError(f"{path}: header declares {evlr_count:,} EVLRs from byte {evlr_start:,}, more than "
                                f"a {file_size:,}-byte file holds after its points (corrupt header)")
    if chunk_size is not None:
        points = (field(head, POINT_COUNT_14_AT, 8) if minor >= 4 else 0) or field(head, LEGACY_COUNT_AT, 4)
        check_chunk_table(path, stream, point_offset, file_size, points, chunk_size)


def laszip_chunk_size(path: Path, stream: BinaryIO, header_size: int, vlr_count: int, point_offset: int) -> int | None:
    """Walk the VLRs, each of which must end by the point data's start; the laszip VLR's chunk size
    (VARIABLE_CHUNKS for variable chunks), or None when there is none (uncompressed LAS)."""
    position, chunk_size = header_size, None
    for number in range(1, vlr_count + 1):
        stream.seek(position)
        fixed = stream.read(VLR_HEADER_BYTES)
        if len(fixed) < VLR_HEADER_BYTES:
            raise PipelineError(f"{path}: VLR {number} of {vlr_count} is cut short (truncated file?)")
        length = int.from_bytes(fixed[VLR_LENGTH_AT:VLR_LENGTH_AT + 2], "little")
        if fixed[2:18].rstrip(b"\x00") == LASZIP_USER and length >= LASZIP_CHUNK_SIZE_AT + 4:
            chunk_size = int.from_bytes(stream.read(LASZIP_CHUNK_SIZE_AT + 4)[LASZIP_CHUNK_SIZE_AT:], "little")
        position += VLR_HEADER_BYTES + length
        if position > point_offset:
            raise PipelineError(f"{path}: VLR {number} of {vlr_count} runs past the start of the point data "
                                f"(byte {point_offset:,}): corrupt header, points would be read from VLR bytes")
    return chunk_size


def check_chunk_table(path: Path, stream: BinaryIO, point_offset: int, file_size: int, points: int,
                      chunk_size: int) -> None:
    """A LAZ chunk table's chunk count agrees with the points (one chunk per chunk_size points, or at most
    one per point for variable chunks): lazrs allocates that many entries and a corrupt count aborts
    the whole process (SIGABRT, no error to catch). A table pointer lazrs cannot follow is its own error."""
    stream.seek(point_offset)
    pointer = int.from_bytes(stream.read(8), "little", signed=True)
    if not point_offset + 8 <= pointer <= file_size - CHUNK_TABLE_HEADER_BYTES:
        return  # no table where it says (old LAZ writers, or corrupt): lazrs reports it as an IoError
    stream.seek(pointer + 4)  # after the table's version
    chunks = int.from_bytes(stream.read(4), "little")
    most = max(points, 1) if chunk_size == VARIABLE_CHUNKS else -(-points // max(chunk_size, 1)) + 1
    if chunks > most:
        raise PipelineError(f"{path}: LAZ chunk table lists {chunks:,} chunks for {points:,} points (at most "
                            f"{most:,}): corrupt file")


def field(head: bytes, offset: int, size: int) -> int:
    """An unsigned little-endian header field (0 where the header is too short to hold it)."""
    return int.from_bytes(head[offset:offset + size], "little") if len(head) >= offset + size else 0


def check_las_header(path: Path, header: laspy.LasHeader, file_size: int) -> None:
    """Scale, offset and bounds are finite (scale non-zero), and an uncompressed file holds every point it declares."""
    scales = np.asarray(header.scales, dtype=np.float64)
    if not (np.isfinite(scales).all() and (scales != 0).all()):
        raise PipelineError(f"{path}: header scale {scales.tolist()} must be finite and non-zero")
    offsets = np.asarray(header.offsets, dtype=np.float64)
    if not np.isfinite(offsets).all():
        raise PipelineError(f"{path}: header offset {offsets.tolist()} is not finite")
    with np.errstate(over="ignore"):
        reach = np.abs(scales) * np.iinfo(np.int32).max + np.abs(offsets)
    if not np.isfinite(reach).all():
        raise PipelineError(f"{path}: header scale {scales.tolist()} overflows floating point coordinates")
    if not (np.isfinite(header.mins).all() and np.isfinite(header.maxs).all()):
        raise PipelineError(f"{path}: header bounds {list(header.mins)} .. {list(header.maxs)} are not finite")
    if header.are_points_compressed:
        return
    available = max(file_size - header.offset_to_point_data, 0) // header.point_format.size
    if available < header.point_count:
        raise PipelineError(f"{path}: header says {header.point_count:,} points but the file holds only "
                            f"{available:,} (truncated file or wrong point count)")


def bounds_encodable(header: laspy.LasHeader) -> bool:
    """Whether the header's XY bounds lie where its scale and offset can put a point (int32 steps from the
    offset, with the usual slack): bounds beyond that reach are not the points' (e.g. near float max),
    and a grid built from them would be absurd, so they are measured from the points instead."""
    scales = np.abs(np.asarray(header.scales[:2], np.float64))
    offsets = np.asarray(header.offsets[:2], np.float64)
    reach = scales * float(np.iinfo(np.int32).max) * (1 + BOUNDS_SLACK_SHARE) + BOUNDS_SLACK_STEPS * scales
    mins, maxs = np.asarray(header.mins[:2], np.float64), np.asarray(header.maxs[:2], np.float64)
    return bool((mins >= offsets - reach).all() and (maxs <= offsets + reach).all() and (mins <= maxs).all())


class OutsideBounds(PipelineError):
    """Points lie outside their file's header bounds (so the header's bounds are wrong)."""


def check_points(path: Path, xyz: np.ndarray, header: laspy.LasHeader) -> None:
    """Decoded coordinates are finite and inside the header's XY bounds, from which the tile grid is built."""
    if not np.isfinite(xyz).all():
        raise PipelineError(f"{path}: NaN or infinite coordinates")
    if len(xyz) == 0:
        return
    mins, maxs = np.asarray(header.mins[:2], np.float64), np.asarray(header.maxs[:2], np.float64)
    slack = np.maximum(BOUNDS_SLACK_STEPS * np.abs(np.asarray(header.scales[:2], np.float64)),
                       BOUNDS_SLACK_SHARE * (maxs - mins))
    low, high = column_min(xyz[:, :2]), column_max(xyz[:, :2])
    if (low < mins - slack).any() or (high > maxs + slack).any():
        raise OutsideBounds(
            f"{path}: points lie outside the header's bounds (x {low[0]:.3f}..{high[0]:.3f}, y {low[1]:.3f}.."
            f"{high[1]:.3f}; header x {mins[0]:.3f}..{maxs[0]:.3f}, y {mins[1]:.3f}..{maxs[1]:.3f}): repair the "
            f"header first (e.g. lasinfo -repair_bb, or pdal translate IN OUT)")
