"""`pipeline.simplify`: the file pipeline for a cloud already in memory (a numpy array or a laspy.LasData),
returning which points to keep instead of writing them.

The cloud goes through a temporary LAS file and a zarr output, so tiles, budgets, seams and seeds are
exactly those of `pipeline run` on the same points; each point carries its index as an extra dimension.
"""
from __future__ import annotations

import copy
import re
import tempfile
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any

import laspy
import numpy as np
import zarr

from model.methods import Method
from pipeline.config import build_config
from pipeline.engine.runner import run_scan
from pipeline.errors import PipelineError, PipelineNote
from pipeline.io.output_meta import priority_fraction

if TYPE_CHECKING:
    from dask.distributed import Client

INDEX_DIMENSION = "simplify_source_index"
RESUME_CLAUSE = re.compile(r" \(finished work kept in .*: re-run the same command to resume\)$")
ARRAY_SCALE = 1e-4  # grid step of an (n, 3) array written to LAS: 0.1 mm, finer than any scanner


def simplify(points: np.ndarray | laspy.LasData, ratio: float, *, method: str | Method = "learned",
             config: str | None = None, client: Client | None = None, **settings: Any) -> np.ndarray:
    """(k,) int64 indices of the points to keep, k = round(ratio * n), most important first.

    `points` is an (n, 3) array of coordinates (metres, or the unit of its CRS; quantised to 0.1 mm) or a
    `laspy.LasData` (its own grid, CRS and classes: `keep_classes` works on it). Settings are those of
    `pipeline.run` (`method` a name or a model.methods object); `client` reuses a Dask client instead of starting a local cluster. The order is the
    progressive one: any prefix is a coarser, spread-out simplification (tile by tile, a point's rank is
    its place in its tile's own order, as a fraction of what the tile keeps).
    """
    run_config = build_config(config, ratio=ratio, method=method, **settings)  # a bad setting before any work
    with tempfile.TemporaryDirectory(prefix="lidar-simplify-") as folder:
        source = Path(folder) / "cloud.las"
        _write_indexed(points, source)
        output = Path(folder) / "kept.zarr"
        try:
            run_scan([source], output, run_config, client=client,
                     note=lambda line: warnings.warn(line.replace(str(source), "the points"), PipelineNote,
                                                     stacklevel=4))
        except PipelineError as exc:  # about the caller's points, not a temporary file (gone, with any work kept)
            raise PipelineError(RESUME_CLAUSE.sub("", str(exc)).replace(str(source), "the points")) from None
        group = zarr.open_group(str(output), mode="r")
        index = np.asarray(group[INDEX_DIMENSION][:], dtype=np.int64)
        counts = np.asarray(group["tile_count"][:], dtype=np.int64)
    return index[progressive_order(counts)]


def progressive_order(counts: np.ndarray) -> np.ndarray:
    """(sum(counts),) an order of tile-after-tile outputs by each point's fractional rank (i + 0.5) / count
    in its tile, ties in tile order: every prefix takes each tile's best points in proportion."""
    rank = np.concatenate([priority_fraction(int(c)) for c in counts]) if len(counts) else np.empty(0)
    return np.argsort(rank, kind="stable")


def _write_indexed(points: np.ndarray | laspy.LasData, path: Path) -> None:
    """Write the cloud to a LAS file with each point's index in an extra dimension."""
    if isinstance(points, laspy.LasData):
        point_format = copy.deepcopy(points.header.point_format)
        if INDEX_DIMENSION in point_format.extra_dimension_names:  # a cloud read from an earlier simplify's file
            point_format.remove_extra_dimension(INDEX_DIMENSION)
        header = laspy.LasHeader(version=points.header.version, point_format=point_format)
        header.scales, header.offsets = points.header.scales, points.header.offsets
        crs_records = [*points.header.vlrs, *(points.header.evlrs or [])]  # LAS 1.4 may hold its WKT in an EVLR
        header.vlrs.extend(v for v in crs_records if v.user_id == "LASF_Projection")
        records = points.points.array
        count = len(records)
        if count == 0:
            raise PipelineError("points: the LasData holds no points (nothing to simplify)")
    else:
        xyz = np.asarray(points, dtype=np.float64)
        if xyz.ndim != 2 or xyz.shape[1] != 3:
            raise PipelineError(f"points must be an (n, 3) array of coordinates, got shape {xyz.shape}")
        if not np.isfinite(xyz).all():
            raise PipelineError("points hold NaN or infinite coordinates")
        if len(xyz) == 0:
            raise PipelineError("points: the array holds no points (nothing to simplify)")
        header = laspy.LasHeader(version="1.4", point_format=6)
        header.offsets = xyz.min(axis=0) if len(xyz) else np.zeros(3)
        span = float((xyz.max(axis=0) - header.offsets).max()) if len(xyz) else 0.0
        header.scales = [max(ARRAY_SCALE, span / 2e9)] * 3  # the integers must fit in int32
        records, count = None, len(xyz)
    header.add_extra_dim(laspy.ExtraBytesParams(INDEX_DIMENSION, "u8", "index in the caller's cloud"))
    las = laspy.LasData(header)
    if records is not None:
        las.points = laspy.ScaleAwarePointRecord.zeros(count, header=header)
        for name in records.dtype.names:
            las.points.array[name] = records[name]
    else:
        las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las[INDEX_DIMENSION] = np.arange(count, dtype=np.uint64)
    las.write(path)
