"""LAS/LAZ/COPC input read in chunks with laspy+lazrs, errors turned into one-line PipelineErrors."""
from __future__ import annotations

import copy
import os
import sys
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import laspy
import numpy as np

from pipeline.errors import PipelineError, is_fatal_signal


def describe_failure(path: Path, exc: BaseException) -> PipelineError:
    """One line naming the file and what laspy/lazrs said (PanicException included)."""
    detail = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return PipelineError(f"{path}: cannot read LAS/LAZ data: {detail}")


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
        if not path.is_file():
            raise PipelineError(f"{path}: no such file")
        try:
            with laspy.open(path) as reader:
                self.header: laspy.LasHeader = copy.deepcopy(reader.header)
        except BaseException as exc:  # lazrs raises PanicException, a BaseException
            if is_fatal_signal(exc):
                raise
            raise describe_failure(path, exc) from None

    @property
    def point_count(self) -> int:
        """Points the header claims (the data may hold fewer if the file is truncated)."""
        return int(self.header.point_count)

    def read(self, start: int, count: int) -> np.ndarray:
        """Raw point records [start, start+count) in laspy's structured dtype (LAZ seeks by chunk table)."""
        try:
            with native_panics_silenced(), laspy.open(self.path) as reader:
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
