"""The temporary on-disk store of the bucketed scan: a folder with one raw file of rows per piece.

A row is the raw LAS record bytes, then the point's global index (int64, little endian). Rows are
sorted by grid cell, so a tile's core+halo is a few row ranges of each piece; ranges are read in
piece order, which keeps a tile's points in file order whatever worker wrote them. A range is one seek
and one read: a zarr array here cost 0.25 s of import a run and about a millisecond a read, for rows no
other tool ever opens. `store.json` holds the record layout and what the creator stored beside it.
"""
from __future__ import annotations

import json
import os
import threading
from collections import OrderedDict
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Callable, Iterator, Sequence

import numpy as np

from model.rules import record_bytes

ROW_CHUNK = 65536
TAIL = 8  # the global index after each record
META = "store.json"
INDEX_FIELD = "__global_index__"  # the row's tail, named in a row's structured view


@dataclass(frozen=True)
class StoredPoints:
    """Points read back from the store: raw records and their global indices. A filter (TileStore.load's
    `keep`) sees `records` as a view of the stored rows, with the record's fields and one more."""

    records: np.ndarray
    index: np.ndarray


@dataclass(frozen=True)
class Slice:
    """Rows [start, stop) of piece `piece`'s array, or of its crowded-cell copy (sorted by sub-cell)."""

    piece: int
    start: int
    stop: int
    crowded: bool = False

    @property
    def array(self) -> str:
        """The name of the stored array the rows are in."""
        return array_name(self.piece, self.crowded)


def array_name(piece: int, crowded: bool = False) -> str:
    """Piece n's rows are file `pn.rows`; its rows in crowded cells, sorted by sub-cell, are `cn.rows`."""
    return f"{'c' if crowded else 'p'}{piece}.rows"


class ChunkCache:
    """Row chunks of stored pieces kept in memory up to a byte budget, least recently used dropped first.

    A tile needs a dozen row ranges of each piece it touches, and the next tile (tiles run in grid
    order) mostly the same chunks; a read is a system call or two. Caching chunks, not whole
    pieces, reads only what tiles touch and keeps the budget small whatever the scan's size.
    """

    def __init__(self) -> None:
        self._arrays: OrderedDict[tuple[str, str, int], np.ndarray] = OrderedDict()
        self._bytes = 0
        self.reads = 0  # chunks read from the store by this process (a cache miss each)
        self._lock = threading.Lock()  # an in-process run's task threads share the cache

    def get(self, key: tuple[str, str, int], budget: int, read: Callable[[], np.ndarray]) -> np.ndarray:
        """The cached chunk, or read it and cache it if it fits the budget (evicting older chunks)."""
        with self._lock:
            if key in self._arrays:
                self._arrays.move_to_end(key)
                return self._arrays[key]
            for stale in [k for k in self._arrays if k[0] != key[0]]:  # chunks of an earlier run in this process
                self._drop(stale)
        array = read()  # outside the lock: two threads may read one chunk at once, never wait for each other
        with self._lock:
            self.reads += 1
            if key not in self._arrays and array.nbytes <= budget:
                while self._arrays and self._bytes + array.nbytes > budget:
                    self._drop(next(iter(self._arrays)))
                self._arrays[key] = array
                self._bytes += array.nbytes
        return array

    def _drop(self, key: tuple[str, str, int]) -> None:
        self._bytes -= self._arrays.pop(key).nbytes


CHUNKS = ChunkCache()  # one per process: a Dask worker keeps it across the tasks of a run


def joined(parts: Sequence[StoredPoints]) -> StoredPoints:
    """Several parts' points, one after another."""
    if len(parts) == 1:
        return parts[0]
    return StoredPoints(np.concatenate([p.records for p in parts]), np.concatenate([p.index for p in parts]))


def encode_rows(records: np.ndarray, index: np.ndarray, order: np.ndarray | None = None) -> np.ndarray:
    """Records plus global index, one uint8 row per point; with `order`, the rows of records[order] and
    index[order]. Rows are filled through a two-field view (record bytes, index), each record's bytes
    gathered whole: a structured array's own fancy index copies field by field (a 500k-point piece of bcts
    bucketed in 114-194 ms that way), a (n, bytes) take into the rows' strided columns took 15 ms, this 9."""
    width = records.dtype.itemsize
    source = record_bytes(records).view(np.dtype((np.void, width))).ravel()
    rows = np.empty((len(records), width + TAIL), dtype=np.uint8)
    fields = rows.view(np.dtype([("record", (np.void, width)), ("index", "<i8")])).ravel()
    fields["record"] = source if order is None else source[order]
    fields["index"] = index if order is None else np.asarray(index)[order]
    return rows


def _descr(dtype: np.dtype) -> str:
    return json.dumps(np.lib.format.dtype_to_descr(dtype))


def _dtype(descr: str) -> np.dtype:
    return np.lib.format.descr_to_dtype([tuple(f) for f in json.loads(descr)])


class TileStore:
    """Writer (one file of rows per piece) and reader (a tile from its slices) of the bucketed scan."""

    def __init__(self, path: Path, record_dtype: np.dtype, attrs: dict) -> None:
        self.path = path
        self.record_dtype = record_dtype
        self.row_bytes = record_dtype.itemsize + TAIL
        self.row_dtype = row_dtype(record_dtype)
        self._attrs = attrs

    @classmethod
    def create(cls, path: Path, record_dtype: np.dtype, attrs: dict) -> "TileStore":
        """A new, empty store at path (replacing any leftover one)."""
        path.mkdir(parents=True, exist_ok=True)
        for stale in path.iterdir():
            stale.unlink()
        meta = {**attrs, "record_dtype": _descr(record_dtype)}
        _replace(path / META, json.dumps(meta).encode())
        return cls(path, record_dtype, attrs)

    @classmethod
    def exists(cls, path: Path) -> bool:
        """Whether a store was created at path (a resumed run keeps the pieces stored in it)."""
        return (path / META).is_file()

    @classmethod
    def open(cls, path: Path) -> "TileStore":
        """An existing store, for writing pieces or reading tiles (in workers)."""
        meta = json.loads((path / META).read_text())
        return cls(path, _dtype(meta.pop("record_dtype")), meta)

    @classmethod
    def reader(cls, path: Path) -> "TileStore":
        """An existing store for reading tiles, opened once per process. Keyed by its metadata file's
        identity, so a store made again at the same path (a new run) is opened again."""
        meta = (path / META).stat()
        return _opened_reader(str(path), meta.st_ino, meta.st_mtime_ns)

    @property
    def attrs(self) -> dict:
        """What the creator stored beside the rows (scales, offsets, ...)."""
        return dict(self._attrs)

    def write_piece(self, piece: int, rows: np.ndarray, crowded: bool = False) -> None:
        """Store one bucketed piece's (n, row_bytes) uint8 rows, or (`crowded`) its copy of the rows in
        crowded cells; written beside and renamed, so a piece file is whole or absent."""
        _replace(self.path / array_name(piece, crowded), np.ascontiguousarray(rows, dtype=np.uint8).data)

    def _read(self, name: str, start: int, stop: int) -> np.ndarray:
        """Rows [start, stop) of a stored file, (stop - start, row_bytes) uint8."""
        rows = np.empty((stop - start, self.row_bytes), dtype=np.uint8)
        with open(self.path / name, "rb") as file:
            file.seek(start * self.row_bytes)
            got = file.readinto(memoryview(rows).cast("B"))
        if got != rows.nbytes:
            raise OSError(f"{self.path / name}: rows {start}..{stop} asked, the file ends first (scratch damaged?)")
        return rows

    def _cached_rows(self, s: Slice, cache_bytes: int) -> Iterator[np.ndarray]:
        """The slice's rows, chunk by chunk through the process's chunk cache."""
        for chunk in range(s.start // ROW_CHUNK, (s.stop - 1) // ROW_CHUNK + 1):
            first = chunk * ROW_CHUNK
            rows = CHUNKS.get((str(self.path), s.array, chunk), cache_bytes,
                              lambda: self._read(s.array, first, min(first + ROW_CHUNK, self._rows(s.array))))
            yield rows[max(s.start - first, 0):s.stop - first]

    def _rows(self, name: str) -> int:
        """Rows in a stored file."""
        return (self.path / name).stat().st_size // self.row_bytes

    def stream(self, slices: Sequence[Slice], cache_bytes: int = 0) -> Iterator[StoredPoints]:
        """The rows of the given slices in the order given, a row chunk (at most ROW_CHUNK rows) at a time:
        a reader that keeps only some of them never holds more than a chunk besides what it keeps."""
        return map(self._points, self._row_chunks(slices, cache_bytes))

    def _row_chunks(self, slices: Sequence[Slice], cache_bytes: int) -> Iterator[np.ndarray]:
        """The slices' stored rows, (m, row_bytes) uint8 a row chunk at most at a time, in the order given."""
        for s in slices:
            if s.stop <= s.start:
                continue
            if cache_bytes > 0:
                yield from self._cached_rows(s, cache_bytes)
            else:
                for first in range(s.start, s.stop, ROW_CHUNK):
                    yield self._read(s.array, first, min(first + ROW_CHUNK, s.stop))

    def load(self, slices: Sequence[Slice], cache_bytes: int = 0,
             keep: Callable[[StoredPoints], np.ndarray] | None = None) -> StoredPoints:
        """The rows of the given slices, in the order given; row chunks are cached up to cache_bytes. With
        `keep` (a row chunk's points -> a boolean mask), only the rows it keeps, chunk by chunk, so the
        memory is what is kept, not what the slices span."""
        parts = list(self.stream(slices, cache_bytes) if keep is None else self._kept(slices, cache_bytes, keep))
        if not parts:
            return self._points(np.empty((0, self.row_bytes), np.uint8))
        return joined(parts)

    def _kept(self, slices: Sequence[Slice], cache_bytes: int,
              keep: Callable[[StoredPoints], np.ndarray]) -> Iterator[StoredPoints]:
        """What `keep` keeps of the slices' rows, filtered about ROW_CHUNK rows at a time (small slices
        gathered first: a filter call costs about as much for 100 rows as for 10,000). The filter reads
        the rows in place (a structured view); only the rows it keeps become records."""
        batch: list[np.ndarray] = []
        count = 0
        for rows in self._row_chunks(slices, cache_bytes):
            batch.append(rows)
            count += len(rows)
            if count >= ROW_CHUNK:
                yield self._filtered(batch, keep)
                batch, count = [], 0
        if batch:
            yield self._filtered(batch, keep)

    def _filtered(self, batch: Sequence[np.ndarray], keep: Callable[[StoredPoints], np.ndarray]) -> StoredPoints:
        """The points of some row chunks that `keep` keeps, told apart on a view of the rows (no copy where it
        keeps them all, as for every load of a method that reads no halo)."""
        rows = np.concatenate(batch) if len(batch) > 1 else np.ascontiguousarray(batch[0])
        view = rows.view(self.row_dtype).ravel()
        kept = keep(StoredPoints(view, view[INDEX_FIELD]))
        return self._points(rows if kept.all() else rows[kept])

    def _points(self, rows: np.ndarray) -> StoredPoints:
        """Records and global indices of stored rows."""
        records = np.ascontiguousarray(rows[:, :-TAIL]).view(self.record_dtype).ravel()
        index = np.ascontiguousarray(rows[:, -TAIL:]).view("<i8").ravel()
        return StoredPoints(records, index)


def row_dtype(record_dtype: np.dtype) -> np.dtype:
    """A stored row as one structured item: the record's fields where they lie, and the global index
    after them (INDEX_FIELD), so a chunk of rows is read as points without a copy."""
    names = list(record_dtype.names)
    return np.dtype({"names": [*names, INDEX_FIELD],
                     "formats": [record_dtype.fields[name][0] for name in names] + ["<i8"],
                     "offsets": [record_dtype.fields[name][1] for name in names] + [record_dtype.itemsize],
                     "itemsize": record_dtype.itemsize + TAIL})


def _replace(path: Path, data: memoryview | bytes) -> None:
    """Write `data` to path through a temporary beside it (through the file object: a full disk says so)."""
    temporary = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
    try:
        with open(temporary, "wb") as file:
            file.write(data)
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)


@lru_cache(maxsize=4)
def _opened_reader(path: str, inode: int, modified_ns: int) -> TileStore:
    """TileStore.open, kept for the few stores a process reads from (inode and mtime only key the cache)."""
    return TileStore.open(Path(path))
