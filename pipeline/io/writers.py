"""Output writers: LAS/LAZ with the input's header here, zarr in pipeline.io.zarr_output; chosen by suffix."""
from __future__ import annotations

import io
from contextlib import ExitStack
from pathlib import Path
from typing import Iterable, Iterator

import laspy
import numpy as np

from pipeline.errors import PipelineError, file_system_error, raise_stop_behind
from pipeline.io.atomic import atomic_output
from pipeline.io.copc_output import clear_min_max, write_copc
from pipeline.io.output_meta import OutputMeta
from pipeline.io.provenance import stamped_header
from tiling.assemble import TilePart

COPC_SUFFIX = ".copc.laz"
OUTPUT_KINDS = (COPC_SUFFIX, ".las", ".laz", ".zarr")  # what an output's name may end in (.copc.laz before .laz)


def output_kind(path: Path) -> str | None:
    """The format an output's name ends in (one of OUTPUT_KINDS, in any case), or None: the one rule for
    choosing a writer, checking an output name and naming `--levels` files."""
    name = path.name.lower()
    return next((kind for kind in OUTPUT_KINDS if name.endswith(kind)), None)


def write_output(path: Path, header: laspy.LasHeader, total: int, parts: Iterable[TilePart], meta: OutputMeta,
                 renamed: ExitStack | None = None) -> int:
    """Write the parts to path (by suffix) through a temporary name; return the points written. With `renamed`,
    the temporary is renamed into place only when that stack closes, with every other output it holds (a run's
    levels: one that fails in its last level leaves none, where it left the others, which its resume refused).

    A write that fails (a full disk) leaves nothing under either name and is reported against `path`.
    """
    kind = output_kind(path)
    if kind is None:
        raise PipelineError(f"{path}: unsupported output type {path.suffix.lower() or '(none)'} "
                            f"(use {', '.join(OUTPUT_KINDS)})")
    try:
        with ExitStack() as own:
            temporary = (renamed or own).enter_context(atomic_output(path))
            if kind == ".zarr":
                from pipeline.io.zarr_output import write_zarr  # here: zarr's import is 0.25 s a LAS run never needs

                written = write_zarr(temporary, header, total, parts, meta)
            elif kind == COPC_SUFFIX:
                written = write_copc(temporary, stamped_header(header, meta), total, parts, meta)
            else:
                written = _write_las(temporary, stamped_header(header, meta), parts, compress=kind == ".laz")
    except OSError as exc:
        raise file_system_error(exc, path) from None
    return written


COMPRESS_ROWS = 200_000  # records per LAZ write: four of lazrs's 50k-point chunks, compressed side by side
# (283k points of bcts in 3k-point tiles: 98-106 ms in one call per tile, 62-72 ms so, the same bytes)


def batched(records: Iterable[np.ndarray], rows: int) -> Iterator[np.ndarray]:
    """The records (structured arrays of one dtype) joined into arrays of at least `rows` rows (the last
    may hold fewer), in order: the writer's memory grows by one batch, not with the output."""
    pending: list[np.ndarray] = []
    count = 0
    for part in records:
        pending.append(part)
        count += len(part)
        if count >= rows:
            yield np.concatenate(pending) if len(pending) > 1 else pending[0]
            pending, count = [], 0
    if pending:
        yield np.concatenate(pending) if len(pending) > 1 else pending[0]


class RecordingFile(io.FileIO):
    """A file opened for writing that keeps the OSError of a failed write (a full disk): lazrs reports
    one only as 'IoError: Failed to call write', which names neither the cause nor the file."""

    def __init__(self, path: Path) -> None:
        super().__init__(path, "w")
        self.error: OSError | None = None

    def write(self, data: bytes) -> int:  # type: ignore[override]
        try:
            return super().write(data)
        except OSError as exc:
            self.error = exc
            raise


def _write_las(path: Path, header: laspy.LasHeader, parts: Iterable[TilePart], compress: bool) -> int:
    """Stream the parts into a LAS/LAZ file, then the input's EVLRs; laspy fills in count and bounds on close.
    LAZ is given COMPRESS_ROWS records at a time: lazrs compresses the whole chunks of one call in parallel,
    and a tile's few thousand complete none alone."""
    written = 0
    evlrs = header.evlrs
    # laspy 2.7 would track each extra-bytes field's min and max as it writes, but gets them wrong: a field with a
    # no-data value keeps its placeholders (min 2^64-1, max 0: the extra-bytes file's Deviation), others a min
    # above the data's; they are marked absent, as in COPC outputs
    clear_min_max(header.vlrs)
    raw = RecordingFile(path)
    records = (part.records for part in parts)
    try:
        with io.BufferedWriter(raw) as stream, \
                laspy.open(stream, mode="w", header=header, do_compress=compress, closefd=False) as writer:
            for batch in batched(records, COMPRESS_ROWS) if compress else records:
                writer.write_points(laspy.PackedPointRecord(batch, header.point_format))
                written += len(batch)
            if evlrs:
                writer.write_evlrs(evlrs)
    except Exception as exc:
        if raw.error is not None:
            raise raw.error from None
        raise_stop_behind(exc)
        raise
    return written
