"""Input checks that fail fast with one line naming the file: paths, LAS headers, decoded points, the scan.

Everything the tile grid relies on is checked here: finite scale/offset/bounds, a point count the data
can hold, points inside the header's bounds, and coordinates in metres rather than degrees.
"""
from __future__ import annotations

import shutil
from pathlib import Path
from typing import TYPE_CHECKING

import laspy
import numpy as np

from pipeline.crs import degrees_reason
from pipeline.errors import PipelineError
from tiling.store import TAIL

if TYPE_CHECKING:
    from pipeline.scan import Scan

LAS_PREAMBLE_BYTES = 104  # the LAS header up to and including its VLR count
VERSION_OFFSET = 24        # major, then minor
VLR_COUNT_OFFSET = 100
VLR_HEADER_BYTES = 54     # the fixed part of every VLR
PROBE_POINTS = 1_000      # points of each file decoded before any worker starts
BOUNDS_SLACK_STEPS = 100  # points may stray this many grid steps (scale) outside the header's bounds ...
BOUNDS_SLACK_SHARE = 0.01  # ... or this share of its extent, whichever is larger
REPROJECT_ADVICE = ("tile size, overlap and neighbourhoods are in metres: reproject to a projected CRS first "
                    "(e.g. pdal translate IN OUT reprojection --filters.reprojection.out_srs=EPSG:<UTM zone>) "
                    "or pass --allow-geographic to run in degrees anyway")


def check_input_path(path: Path) -> None:
    """The input exists and is a regular file (not a folder, a device or a missing name)."""
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
    low, high = xyz[:, :2].min(axis=0), xyz[:, :2].max(axis=0)
    if (low < mins - slack).any() or (high > maxs + slack).any():
        raise OutsideBounds(
            f"{path}: points lie outside the header's bounds (x {low[0]:.3f}..{high[0]:.3f}, y {low[1]:.3f}.."
            f"{high[1]:.3f}; header x {mins[0]:.3f}..{maxs[0]:.3f}, y {mins[1]:.3f}..{maxs[1]:.3f}): repair the "
            f"header first (e.g. lasinfo -repair_bb, or pdal translate IN OUT)")


def check_run(scan: "Scan", allow_degrees: bool, scratch: Path) -> None:
    """Before any worker starts: no input in degrees (unless allowed), the first points of every file decode,
    and the scratch folder has room for the bucketed scan (every record, uncompressed, with its index)."""
    for source in scan.sources:
        reason = degrees_reason(source.header)
        if reason and not allow_degrees:
            raise PipelineError(f"{source.path}: {reason}; {REPROJECT_ADVICE}")
    scan.probe(PROBE_POINTS)
    if not scratch.is_dir():
        raise PipelineError(f"{scratch}: scratch folder does not exist")
    need, free = scan.point_count * (scan.dtype.itemsize + TAIL), shutil.disk_usage(scratch).free
    if free < need:
        raise PipelineError(f"{scratch}: not enough space left for the scratch tiles ({free / 2**20:.1f} MiB free, "
                            f"about {need / 2**20:.1f} MiB needed): pass --scratch a folder on a larger disk")
