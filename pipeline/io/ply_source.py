"""PLY point clouds read as LAS 1.4 point format 7 records, chunk by chunk (which property goes where:
pipeline.io.ply_schema)."""
from __future__ import annotations

from pathlib import Path

import laspy
import numpy as np
from plyfile import PlyData, PlyElement, PlyParseError

from model.rules import grid_ints
from pipeline.errors import PipelineError
from pipeline.io.ply_schema import XYZ, Converter, PlySchema, colour_converter

PLY_SCALE = 0.001  # millimetre grid: finer than any mobile scanner's range noise


class PlySource:
    """A binary or ASCII PLY 'vertex' element; binary files are memory-mapped, never loaded whole."""

    def __init__(self, path: Path, chunk: int = 1_000_000) -> None:
        self.path = path
        self._vertices = self._open_vertices()
        self.schema = PlySchema.of(self._vertices.data.dtype, str(path))
        self._colours: dict[str, Converter] = {}
        self.header = self._make_header(chunk)

    def _open_vertices(self) -> PlyElement:
        try:
            return PlyData.read(str(self.path), mmap=True)["vertex"]
        except (PlyParseError, KeyError, ValueError, OSError) as exc:
            raise PipelineError(f"{self.path}: cannot read PLY vertices: {exc}") from None

    def __getstate__(self) -> dict:
        """Pickle without the memory map (workers reopen the file), so shipping a source is cheap."""
        return {**self.__dict__, "_vertices": None}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._vertices = self._open_vertices()

    @property
    def point_count(self) -> int:
        """Vertices the PLY header declares."""
        return int(self._vertices.count)

    def _column(self, name: str, start: int, stop: int) -> np.ndarray:
        return np.asarray(self._vertices.data[name][start:stop])

    def _make_header(self, chunk: int) -> laspy.LasHeader:
        """A PF7 header on a millimetre grid anchored at the cloud's minimum, found by one streamed pass a column
        at a time (a NaN or infinity shows in a column's minimum or maximum): stacking the columns into rows
        and reducing across them took 0.3 s of bcts_1..4's 2.8M vertices."""
        header = laspy.LasHeader(version="1.4", point_format=7)
        for name, las_name, dtype in self.schema.extras:
            header.add_extra_dim(laspy.ExtraBytesParams(name=las_name, type=dtype,
                                                        description=f"PLY {name}"[:32]))
        mins = np.full(3, np.inf)
        maxs = np.full(3, -np.inf)
        peaks = dict.fromkeys(self.schema.colours, 0.0)  # a float channel's range sets its scale
        for start in range(0, self.point_count, chunk):
            for channel in peaks:
                if self._vertices.data.dtype[channel].kind == "f":
                    column = self._column(channel, start, start + chunk)
                    peaks[channel] = max(peaks[channel], float(np.nanmax(column)) if len(column) else 0.0)
            for axis, name in enumerate(XYZ):
                column = self._column(name, start, start + chunk)
                low, high = float(column.min()), float(column.max())
                if not (np.isfinite(low) and np.isfinite(high)):
                    vertex = start + int(np.flatnonzero(~np.isfinite(column))[0])
                    raise PipelineError(f"{self.path}: NaN or infinite {name} coordinate at vertex {vertex} "
                                        f"(counting from 0)")
                mins[axis], maxs[axis] = min(mins[axis], low), max(maxs[axis], high)
        self._colours = {c: colour_converter(self._vertices.data.dtype[c], peak) for c, peak in peaks.items()}
        if self.point_count:
            header.offsets = np.floor(mins)
            header.scales = np.full(3, PLY_SCALE)
            header.mins, header.maxs = mins, maxs
            widest = float(grid_ints(maxs, header.scales, header.offsets).max())  # the reads rely on it
            if widest > np.iinfo(np.int32).max:
                raise PipelineError(f"{self.path}: the cloud spans {widest * PLY_SCALE:,.0f} along an axis, more than "
                                    f"LAS's 32-bit grid holds at {PLY_SCALE} steps")
        return header

    def read(self, start: int, count: int) -> np.ndarray:
        """Raw PF7 records (with extra bytes for unmapped properties) of vertices [start, start+count)."""
        stop = start + count
        record = laspy.ScaleAwarePointRecord.zeros(count, header=self.header)
        for axis, name in enumerate(XYZ):  # on the grid as laspy's scaled assignment puts them, without its copies
            # and checks (the header fits them in int32): bcts_1..4's 2.8M vertices 0.14-0.33 -> 0.10-0.17 s
            record.array[name.upper()] = grid_ints(self._column(name, start, stop), self.header.scales[axis],
                                                   self.header.offsets[axis])
        for channel, convert in self._colours.items():
            record[channel] = convert(self._column(channel, start, stop))
        for prop, dim, convert in self.schema.mapped:
            record[dim] = convert(self._column(prop, start, stop))
        if self.schema.default_returns:
            record["return_number"] = record["number_of_returns"] = np.ones(count, dtype=np.uint8)
        for prop, las_name, _ in self.schema.extras:
            record[las_name] = self._column(prop, start, stop)
        return record.array
