"""LAS/LAZ/COPC input read in chunks with laspy+lazrs, errors turned into one-line PipelineErrors."""
from __future__ import annotations

import copy
import io
import os
import sys
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import laspy
import numpy as np

from pipeline.errors import PipelineError, is_fatal_signal
from pipeline.validate import LAS_PREAMBLE_BYTES, check_las_header, check_las_preamble


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

    LAZ is decoded by lazrs's single-threaded decompressor: workers run one thread each, and after a seek
    the multi-threaded one returns zero-filled points where a file holds fewer than its header declares.
    """
    with open(path, "rb") as probe:
        head = probe.read(LAS_PREAMBLE_BYTES)
        check_las_preamble(path, head, os.fstat(probe.fileno()).st_size)
    source = io.BufferedReader(Las10AsLas11(path)) if head[24:26] == b"\x01\x00" else path
    return laspy.open(source, laz_backend=laspy.LazBackend.Lazrs)


@contextmanager
def native_panics_silenced() -> Iterator[None]:
    """Send fd 2 to a temporary file while lazrs decodes: a Rust panic prints a many-line report there
    before laspy raises PanicException. The report is dropped on a panic and replayed otherwise."""
    sys.stderr.flush()
    saved = os.dup(2)
    panicked = False
    with tempfile.TemporaryFile() as capture:
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

    def read(self, start: int, count: int) -> np.ndarray:
        """Raw point records [start, start+count) in laspy's structured dtype (LAZ seeks by chunk table)."""
        try:
            with native_panics_silenced(), open_las(self.path) as reader:
                reader.seek(start)
                records = reader.read_points(count).array
        except BaseException as exc:  # lazrs raises PanicException, a BaseException
            if is_fatal_signal(exc):
                raise
            raise describe_failure(self.path, exc) from None
        if len(records) != count:
            raise PipelineError(f"{self.path}: header says {self.point_count} points but the data ends before "
                                f"point {start + count} (truncated file?)")
        return records
