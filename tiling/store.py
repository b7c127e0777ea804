"""The temporary on-disk tile store (zarr v3): one uncompressed 2-D uint8 array per bucketed piece.

A row is the raw LAS record bytes, then the point's global index (int64, little endian), then a core
flag byte. Rows are grouped by tile, so one tile is a slice of each piece that touched it; the slices
are read in piece order, which keeps a tile's points in file order whatever worker wrote them.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import zarr

ROW_CHUNK = 65536
TAIL = 9  # index (8 bytes) + core flag (1 byte) after each record


@dataclass(frozen=True)
class TilePoints:
    """One tile's points as stored: raw records, global indices, and which are core (not halo)."""

    records: np.ndarray
    index: np.ndarray
    core: np.ndarray


@dataclass(frozen=True)
class Slice:
    """Rows [start, stop) of piece `piece`'s array."""

    piece: int
    start: int
    stop: int


def encode_rows(records: np.ndarray, index: np.ndarray, core: np.ndarray) -> np.ndarray:
    """Records plus global index and core flag, one uint8 row per point."""
    rows = np.empty((len(records), records.dtype.itemsize + TAIL), dtype=np.uint8)
    rows[:, :-TAIL] = np.ascontiguousarray(records).view(np.uint8).reshape(len(records), records.dtype.itemsize)
    rows[:, -TAIL:-1] = np.ascontiguousarray(index, dtype="<i8").view(np.uint8).reshape(len(index), 8)
    rows[:, -1] = core
    return rows


def _descr(dtype: np.dtype) -> str:
    return json.dumps(np.lib.format.dtype_to_descr(dtype))


def _dtype(descr: str) -> np.dtype:
    return np.lib.format.descr_to_dtype([tuple(f) for f in json.loads(descr)])


class TileStore:
    """Writer (one array per piece) and reader (a tile from its slices) of the bucketed scan."""

    def __init__(self, path: Path, record_dtype: np.dtype, group: zarr.Group) -> None:
        self.path = path
        self.record_dtype = record_dtype
        self._group = group

    @classmethod
    def create(cls, path: Path, record_dtype: np.dtype, attrs: dict) -> "TileStore":
        """A new, empty store at path (replacing any leftover one)."""
        group = zarr.open_group(str(path), mode="w", zarr_format=3)
        group.attrs.update({**attrs, "record_dtype": _descr(record_dtype)})
        return cls(path, record_dtype, group)

    @classmethod
    def open(cls, path: Path) -> "TileStore":
        """An existing store, for writing pieces or reading tiles (in workers)."""
        group = zarr.open_group(str(path), mode="r+", zarr_format=3)
        return cls(path, _dtype(group.attrs["record_dtype"]), group)

    @property
    def attrs(self) -> dict:
        """What the creator stored beside the rows (scales, offsets, ...)."""
        return dict(self._group.attrs)

    def write_piece(self, piece: int, rows: np.ndarray) -> None:
        """Store one bucketed piece's rows (uncompressed: the store is short-lived and I/O is not the cost)."""
        array = self._group.create_array(f"p{piece}", shape=rows.shape, dtype="uint8", overwrite=True,
                                         chunks=(min(ROW_CHUNK, max(len(rows), 1)), rows.shape[1]),
                                         compressors=None)
        array[:] = rows

    def load(self, slices: Sequence[Slice]) -> TilePoints:
        """A tile's points gathered from its slices, in the order given."""
        parts = [self._group[f"p{s.piece}"][s.start:s.stop] for s in slices if s.stop > s.start]
        rows = np.concatenate(parts) if parts else np.empty((0, self.record_dtype.itemsize + TAIL), np.uint8)
        records = np.ascontiguousarray(rows[:, :-TAIL]).view(self.record_dtype).ravel()
        index = np.ascontiguousarray(rows[:, -TAIL:-1]).view("<i8").ravel()
        return TilePoints(records, index, rows[:, -1].astype(bool))
