"""One logical scan from one or more input files: a common record layout and a chunk stream."""
from __future__ import annotations

import copy
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import laspy
import numpy as np

from model.rules import column_max, column_min, grid_ints, grid_xyz
from pipeline.errors import PipelineError
from pipeline.io.las_source import LasSource
from pipeline.io.output_guard import check_distinct_inputs
from pipeline.io.ply_source import PlySource
from pipeline.io.validate import OutsideBounds, bounds_encodable, check_input_path, check_points

LAS_SUFFIXES = (".las", ".laz")


@dataclass(frozen=True)
class Chunk:
    """Consecutive points of the scan: raw records in the output layout and their float64 xyz."""

    records: np.ndarray
    xyz: np.ndarray


@dataclass(frozen=True)
class Piece:
    """A run of consecutive points of one input file: the unit a worker reads.

    `first` is the scan-wide index of its first point (files are numbered one after another).
    """

    number: int
    source: int
    start: int
    count: int
    first: int


def open_source(path: Path) -> LasSource | PlySource:
    """A reader for one file, chosen by suffix (COPC `.copc.laz` is LAZ)."""
    check_input_path(path)
    suffix = path.suffix.lower()
    if suffix in LAS_SUFFIXES:
        return LasSource(path)
    if suffix == ".ply":
        return PlySource(path)
    raise PipelineError(f"{path}: unsupported input type {suffix or '(none)'} (expected .las, .laz, .copc.laz or .ply)")


def output_header(template: laspy.LasHeader) -> laspy.LasHeader:
    """A copy of the first input's header without COPC records, which would be invalid in a plain LAS/LAZ."""
    header = copy.deepcopy(template)
    for records in (header.vlrs, header.evlrs or []):
        records[:] = [v for v in records if v.user_id != "copc"]
    return header


class Scan:
    """The inputs as one point stream in the first input's point format, scale and offset."""

    def __init__(self, paths: Sequence[str | Path]) -> None:
        if not paths:
            raise PipelineError("no input files given")
        self.sources = [open_source(Path(p)) for p in paths]
        check_distinct_inputs(self.paths)
        first = self.sources[0]
        self.header = output_header(first.header)
        self.point_format = self.header.point_format
        self.dtype = self.point_format.dtype()
        self.scales = np.asarray(self.header.scales, dtype=np.float64)
        self.offsets = np.asarray(self.header.offsets, dtype=np.float64)
        for source in self.sources[1:]:
            fmt = source.header.point_format
            if fmt.id != self.point_format.id or fmt.dtype() != self.dtype:
                raise PipelineError(
                    f"{source.path}: point format {fmt.id} with dimensions {list(fmt.dimension_names)} differs from "
                    f"{first.path}'s format {self.point_format.id}; convert the inputs to one format first")
        if self.point_count == 0:
            raise PipelineError(f"{', '.join(str(s.path) for s in self.sources)}: contains no points")

    @property
    def paths(self) -> list[Path]:
        """The input files in stream order."""
        return [s.path for s in self.sources]

    @property
    def point_count(self) -> int:
        """Total points the headers declare."""
        return sum(s.point_count for s in self.sources)

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Union of the headers' min and max xyz."""
        mins = np.min([s.header.mins for s in self.sources], axis=0)
        maxs = np.max([s.header.maxs for s in self.sources], axis=0)
        return np.asarray(mins, dtype=np.float64), np.asarray(maxs, dtype=np.float64)

    def decode_xyz(self, records: np.ndarray) -> np.ndarray:
        """Float64 coordinates of raw records on this scan's grid."""
        return grid_xyz(records, self.scales, self.offsets)

    def _to_grid(self, records: np.ndarray, source: LasSource | PlySource) -> np.ndarray:
        """Re-quantise another file's X/Y/Z integers onto the first file's scale and offset."""
        scales = np.asarray(source.header.scales, dtype=np.float64)
        offsets = np.asarray(source.header.offsets, dtype=np.float64)
        if np.array_equal(scales, self.scales) and np.array_equal(offsets, self.offsets):
            return records
        records = records.copy()
        for axis, name in enumerate("XYZ"):
            value = records[name].astype(np.float64) * scales[axis] + offsets[axis]
            ints = grid_ints(value, self.scales[axis], self.offsets[axis])
            if np.abs(ints).max(initial=0) > np.iinfo(np.int32).max:
                raise PipelineError(f"{source.path}: coordinates do not fit {self.sources[0].path}'s scale/offset")
            records[name] = ints.astype(np.int32)
        return records

    def pieces(self, size: int) -> list[Piece]:
        """The scan cut into pieces of at most `size` points, in file order, never crossing files."""
        pieces, first = [], 0
        for number_in_source, source in enumerate(self.sources):
            for start in range(0, source.point_count, size):
                count = min(size, source.point_count - start)
                pieces.append(Piece(len(pieces), number_in_source, start, count, first + start))
            first += source.point_count
        return pieces

    def read(self, piece: Piece) -> Chunk:
        """One piece's records on this scan's grid and their xyz, checked finite and inside the file's bounds."""
        source = self.sources[piece.source]
        records = self._to_grid(source.read(piece.start, piece.count), source)
        xyz = self.decode_xyz(records)
        check_points(source.path, xyz, source.header)
        return Chunk(records, xyz)

    def probe(self, count: int, on_file: Callable[[], None] = lambda: None) -> None:
        """Decode the first `count` points of every file, so a corrupt one fails before any worker starts.

        A file whose header bounds miss even those points (bounds written unscaled, as in simple1_3.las)
        gets its bounds measured by one streamed pass, and so does one whose bounds lie beyond what its scale
        and offset can encode (near float max); points that stray later fail in the worker.
        """
        first = 0
        for number, source in enumerate(self.sources):
            on_file()
            if source.point_count and not bounds_encodable(source.header):
                self._measure_bounds(source)
            elif source.point_count:
                try:
                    self.read(Piece(-1, number, 0, min(count, source.point_count), first))  # -1: never stored
                except OutsideBounds:
                    self._measure_bounds(source)
            first += source.point_count

    @staticmethod
    def _measure_bounds(source: LasSource | PlySource, chunk: int = 1_000_000) -> None:
        """Replace the source header's min/max xyz by those of its points, read in chunks."""
        mins, maxs = np.full(3, np.inf), np.full(3, -np.inf)
        scales, offsets = np.asarray(source.header.scales), np.asarray(source.header.offsets)
        for start in range(0, source.point_count, chunk):
            xyz = grid_xyz(source.read(start, min(chunk, source.point_count - start)), scales, offsets)
            mins, maxs = np.minimum(mins, column_min(xyz)), np.maximum(maxs, column_max(xyz))
        source.header.mins, source.header.maxs = mins, maxs
