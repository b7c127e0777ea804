"""LAS/LAZ/COPC input read in chunks with laspy+lazrs, errors turned into one-line PipelineErrors."""
from __future__ import annotations

import copy
from pathlib import Path
from typing import Iterator

import laspy
import numpy as np

from pipeline.errors import PipelineError, is_fatal_signal


def describe_failure(path: Path, exc: BaseException) -> PipelineError:
    """One line naming the file and what laspy/lazrs said (PanicException included)."""
    detail = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return PipelineError(f"{path}: cannot read LAS/LAZ data: {detail}")


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

    def chunks(self, size: int) -> Iterator[np.ndarray]:
        """Raw point records (laspy's structured dtype) in file order, at most `size` at a time."""
        done = 0
        try:
            with laspy.open(self.path) as reader:
                for record in reader.chunk_iterator(size):
                    done += len(record)
                    yield record.array
        except BaseException as exc:
            if is_fatal_signal(exc) or isinstance(exc, GeneratorExit):
                raise
            raise describe_failure(self.path, exc) from None
        if done != self.point_count:
            raise PipelineError(f"{self.path}: header says {self.point_count} points but the data holds {done} (truncated file?)")
