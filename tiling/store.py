"""The temporary on-disk tile store (zarr v3): per tile, its core+halo points with every dimension.

Each tile is one 2-D uint8 array whose rows are the raw LAS record bytes, then the point's global
index (int64, little endian), then a core flag byte: one array per tile keeps appends and reads cheap.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import zarr

ROW_CHUNK = 65536


@dataclass(frozen=True)
class TilePoints:
    """One tile's points as stored: raw records, global indices, and which are core (not halo)."""

    records: np.ndarray
    index: np.ndarray
    core: np.ndarray


def _descr(dtype: np.dtype) -> str:
    return json.dumps(np.lib.format.dtype_to_descr(dtype))


def _dtype(descr: str) -> np.dtype:
    return np.lib.format.descr_to_dtype([tuple(f) for f in json.loads(descr)])


class TileStore:
    """Append-buffered writer and reader of per-tile point rows under one zarr group."""

    def __init__(self, path: Path, record_dtype: np.dtype, group: zarr.Group) -> None:
        self.path = path
        self.record_dtype = record_dtype
        self.row_width = record_dtype.itemsize + 9
        self._group = group
        self._pending: dict[int, list[np.ndarray]] = {}
        self._pending_bytes = 0

    @classmethod
    def create(cls, path: Path, record_dtype: np.dtype, attrs: dict) -> "TileStore":
        """A new, empty store at path (replacing any leftover one)."""
        group = zarr.open_group(str(path), mode="w", zarr_format=3)
        group.attrs.update({**attrs, "record_dtype": _descr(record_dtype)})
        return cls(path, record_dtype, group)

    @classmethod
    def open(cls, path: Path) -> "TileStore":
        """An existing store, for reading tiles (in workers) or finishing a run."""
        group = zarr.open_group(str(path), mode="r+", zarr_format=3)
        return cls(path, _dtype(group.attrs["record_dtype"]), group)

    @property
    def attrs(self) -> dict:
        """What the creator stored beside the tiles (scales, offsets, ...)."""
        return dict(self._group.attrs)

    def add(self, tile_id: int, records: np.ndarray, index: np.ndarray, core: np.ndarray) -> None:
        """Queue rows for a tile; rows reach disk on flush()."""
        rows = np.empty((len(records), self.row_width), dtype=np.uint8)
        rows[:, :-9] = records.view(np.uint8).reshape(len(records), -1)
        rows[:, -9:-1] = index.astype("<i8").view(np.uint8).reshape(-1, 8)
        rows[:, -1] = core
        self._pending.setdefault(tile_id, []).append(rows)
        self._pending_bytes += rows.nbytes

    @property
    def pending_bytes(self) -> int:
        """Bytes queued in memory and not yet written."""
        return self._pending_bytes

    def flush(self) -> None:
        """Append every queued row to its tile's array."""
        for tile_id, parts in sorted(self._pending.items()):
            rows = np.concatenate(parts)
            name = f"t{tile_id}"
            if name in self._group:
                self._group[name].append(rows)
            else:
                array = self._group.create_array(name, shape=(0, self.row_width), chunks=(ROW_CHUNK, self.row_width),
                                                 dtype="uint8")
                array.append(rows)
        self._pending.clear()
        self._pending_bytes = 0

    def load(self, tile_id: int) -> TilePoints:
        """All stored rows of one tile, in the order they were added."""
        rows = self._group[f"t{tile_id}"][:]
        records = np.ascontiguousarray(rows[:, :-9]).view(self.record_dtype).ravel()
        index = np.ascontiguousarray(rows[:, -9:-1]).view("<i8").ravel()
        return TilePoints(records, index, rows[:, -1].astype(bool))
