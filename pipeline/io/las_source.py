"""LAS/LAZ/COPC input read in chunks with laspy+lazrs, errors turned into one-line PipelineErrors."""
from __future__ import annotations

import copy
import io
import os
import sys
import tempfile
import threading
from contextlib import contextmanager
from functools import cached_property
from pathlib import Path
from typing import Iterator

import laspy
import lazrs
import numpy as np

from pipeline.errors import PipelineError, is_fatal_signal, raise_stop_behind
from pipeline.io.validate import (LAS_PREAMBLE_BYTES, VARIABLE_CHUNKS, check_las_header, check_las_layout,
                                  check_las_preamble)


def describe_failure(path: Path, exc: BaseException) -> PipelineError:
    """One line naming the file and what laspy/lazrs said (PanicException included)."""
    detail = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return PipelineError(f"{path}: cannot read LAS/LAZ data (corrupt, truncated or unsupported file?): {detail}")


VERSION_MINOR_OFFSET = 25  # header byte holding the LAS minor version


class Las10AsLas11(io.RawIOBase):
    """A LAS 1.0 file seen as 1.1, whose layout it shares (1.1 only named reserved header fields):
    laspy reads 1.1 to 1.4, so this one header byte is all that stands between it and 1.0 files."""

    def __init__(self, path: Path) -> None:
        self._file = open(path, "rb")

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        return self._file.seek(offset, whence)

    def tell(self) -> int:
        return self._file.tell()

    def readinto(self, buffer: bytearray) -> int:
        start = self._file.tell()
        count = self._file.readinto(buffer)
        if start <= VERSION_MINOR_OFFSET < start + count:
            buffer[VERSION_MINOR_OFFSET - start] = 1
        return count

    def close(self) -> None:
        self._file.close()
        super().close()


def open_las(path: Path) -> laspy.LasReader:
    """laspy's reader on path, with LAS 1.0 files presented as 1.1, once its preamble is checked.

    Its LAZ decoder is lazrs's single-threaded one: after a seek the multi-threaded one returns zero-filled
    points where a file holds fewer than its header declares (LasSource.read decodes whole chunks in
    parallel through the chunk table instead).
    """
    with open(path, "rb") as probe:
        head = probe.read(LAS_PREAMBLE_BYTES)
        check_las_preamble(path, head, os.fstat(probe.fileno()).st_size)
        check_las_layout(path, probe, os.fstat(probe.fileno()).st_size)
    source = io.BufferedReader(Las10AsLas11(path)) if head[24:26] == b"\x01\x00" else path
    return laspy.open(source, laz_backend=laspy.LazBackend.Lazrs)


FD2_REDIRECTED = threading.Lock()  # fd 2 belongs to the whole process: one decode at a time redirects it


@contextmanager
def native_panics_silenced() -> Iterator[None]:
    """Send fd 2 to a temporary file while lazrs decodes: a Rust panic prints a many-line report there
    before laspy raises PanicException. The report is dropped on a panic and replayed otherwise.
    Decodes on other threads of the process (an in-process run) wait: interleaved, one thread's restore
    would leave fd 2 on another's temporary file."""
    with FD2_REDIRECTED, tempfile.TemporaryFile() as capture:
        sys.stderr.flush()
        saved = os.dup(2)
        panicked = False
        os.dup2(capture.fileno(), 2)
        try:
            yield
        except BaseException as exc:
            panicked = type(exc).__name__ == "PanicException"
            raise
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            if not panicked:
                capture.seek(0)
                sys.stderr.write(capture.read().decode(errors="replace"))


class LasSource:
    """One LAS/LAZ file (COPC is read as plain LAZ): its header and its points as raw records."""

    def __init__(self, path: Path) -> None:
        self.path = path
        try:
            with open_las(path) as reader:
                self.header: laspy.LasHeader = copy.deepcopy(reader.header)
        except PipelineError:
            raise
        except BaseException as exc:  # lazrs raises PanicException, a BaseException
            if is_fatal_signal(exc):
                raise
            raise describe_failure(path, exc) from None
        check_las_header(path, self.header, path.stat().st_size)

    @property
    def point_count(self) -> int:
        """Points the header claims (the data may hold fewer if the file is truncated)."""
        return int(self.header.point_count)

    @cached_property
    def chunks(self) -> tuple[list[tuple[int, int]], int] | None:
        """The LAZ chunk table (chunk_table), read once per source; None for LAS, or for a fixed-chunk file
        whose table cannot be read (old writers, truncation): that one is read by seeking, whose short read
        reports the truncation."""
        if laszip_record(self.header) is None:
            return None
        try:
            return chunk_table(self.path, self.header)
        except lazrs.LazrsError:
            if variable_chunks(self.header):
                raise
            return None

    def read(self, start: int, count: int) -> np.ndarray:
        """Raw point records [start, start+count) in laspy's structured dtype. LAZ points of more than one
        chunk are decoded through the chunk table, chunks in parallel (lazrs's threads: bcts_1's 532k points
        in 0.17 s against 0.30 s one chunk after another, on 2 cores), so an in-process run's decodes, which
        go one at a time (FD2_REDIRECTED and the GIL), still use every core; a worker process is held to one
        such thread (pipeline.engine.dask_cluster)."""
        try:
            with native_panics_silenced(), open_las(self.path) as reader:
                chunks = self.chunks
                if chunks is not None and (variable_chunks(self.header) or spans_chunks(self.header, start, count)):
                    records = read_by_chunk_table(self.path, self.header, start, count, chunks)
                else:
                    reader.seek(start)
                    records = reader.read_points(count).array
        except BaseException as exc:  # lazrs raises PanicException, a BaseException
            if is_fatal_signal(exc):
                raise
            raise_stop_behind(exc)  # not a corrupt file: Ctrl-C landed in a read lazrs called
            raise describe_failure(self.path, exc) from None
        if len(records) != count:
            raise PipelineError(f"{self.path}: header says {self.point_count} points but the data ends before "
                                f"point {start + count} (truncated file?)")
        return records


def laszip_record(header: laspy.LasHeader) -> bytes | None:
    """The laszip VLR's payload of a LAZ file's header; None for uncompressed LAS."""
    found = [vlr for vlr in header.vlrs if type(vlr).__name__ == "LasZipVlr"]
    return found[0].record_data if found else None


def variable_chunks(header: laspy.LasHeader) -> bool:
    """Whether a LAZ file's chunks each hold their own number of points (COPC always, some writers too)."""
    laszip = laszip_record(header)
    return laszip is not None and lazrs.LazVlr(laszip).chunk_size() == VARIABLE_CHUNKS


def spans_chunks(header: laspy.LasHeader, start: int, count: int) -> bool:
    """Whether points [start, start+count) of a fixed-chunk LAZ file lie in more than one chunk."""
    size = lazrs.LazVlr(laszip_record(header)).chunk_size()
    return count > 0 and start // size != (start + count - 1) // size


def chunk_table(path: Path, header: laspy.LasHeader) -> tuple[list[tuple[int, int]], int]:
    """A LAZ file's chunks as (points, bytes) each, and the byte where the first starts. lazrs lists each chunk
    of a fixed-size table as full, the last included: here the last holds the points left for it."""
    laszip = lazrs.LazVlr(laszip_record(header))
    with open(path, "rb") as source:
        source.seek(header.offset_to_point_data)
        table = lazrs.read_chunk_table(source, laszip)
        first_byte = source.tell()
    size = laszip.chunk_size()
    if size != VARIABLE_CHUNKS:
        left = int(header.point_count)
        table = [(min(size, max(left - number * size, 0)), length) for number, (_, length) in enumerate(table)]
    return table, first_byte


def read_by_chunk_table(path: Path, header: laspy.LasHeader, start: int, count: int,
                        located: tuple[list[tuple[int, int]], int]) -> np.ndarray:
    """Records [start, start+count) of a LAZ file, decoding only the chunks of its `located` chunk table
    (chunk_table) that hold them. Fewer come back where the table ends first (truncation).

    Variable-chunk files (COPC always, some writers too) are always read so: lazrs's seek assumes equal
    chunks, and on lone-star.copc.laz it returned other points (or failed to fill its buffer) from any
    seek past the first chunk."""
    table, first_byte = located
    points_before = np.concatenate([[0], np.cumsum([points for points, _ in table])])
    byte_at = first_byte + np.concatenate([[0], np.cumsum([size for _, size in table])])
    first = int(np.searchsorted(points_before, start, side="right")) - 1
    last = min(int(np.searchsorted(points_before, start + count, side="left")), len(table))
    first = min(first, last)  # past the table's last point (truncated): nothing, which read() reports
    with open(path, "rb") as source:
        source.seek(int(byte_at[first]))
        compressed = source.read(int(byte_at[last] - byte_at[first]))
    dtype = header.point_format.dtype()
    decoded = bytearray(int(points_before[last] - points_before[first]) * dtype.itemsize)
    lazrs.decompress_points_with_chunk_table(compressed, laszip_record(header), decoded, table[first:last],
                                             lazrs.DecompressionSelection(lazrs.SELECTIVE_DECOMPRESS_ALL))
    skip = start - int(points_before[first])
    return np.frombuffer(decoded, dtype=dtype)[skip:skip + count].copy()
