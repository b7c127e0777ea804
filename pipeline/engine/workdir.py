"""A run's resumable work folder: the bucketed store, each finished piece and tile, and a manifest.

The folder's name holds a key of everything that decides the output (the inputs' paths, sizes and
modification times, the settings, the package version), so re-running the same command after a
crash or a kill finds it and skips the finished work, while a changed command starts afresh. Every
result file is written under a temporary name and renamed: a file that exists is complete.
"""
from __future__ import annotations

import errno
import fcntl
import hashlib
import json
import os
import shutil
import zipfile
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

import numpy as np

from model.registry import changed_parameters
from pipeline.config import RunConfig
from pipeline.errors import PipelineError
from pipeline.io.atomic import atomic_output
from pipeline.io.provenance import weights_digest
from tiling.store import TileStore, array_name
from pipeline.version import __version__

MANIFEST = "manifest.json"
LOCK = "lock"
RESULT_SETTINGS = ("ratio", "method", "tile_size", "overlap", "max_tile_points", "merge_tile_points", "seam_tolerance",
                   "chunk_points", "seed", "keep_classes", "thin_classes", "levels")  # the settings that change the output; workers and memory do not


def output_settings(config: RunConfig) -> dict[str, Any]:
    """The settings that decide the output (not workers or memory, so outputs match whatever runs them),
    with the method's parameters where they differ from its defaults."""
    settings = {name: value for name, value in asdict(config).items() if name in RESULT_SETTINGS}
    if changed := changed_parameters(config.method, config.simplifier):
        settings["method_parameters"] = changed
    return settings


def run_key(inputs: Sequence[Path], config: RunConfig) -> str:
    """A digest of the inputs (resolved path, size, mtime), the output-deciding settings, every parameter
    of the method (read from its fields, so none can be left out; trained weights by their contents' digest,
    not where they lie: weights changed in place would have resumed with the old, and an install moved
    elsewhere would have resumed nothing) and the version."""
    parameters = config.simplifier.parameters()
    if (weights := config.simplifier.trained_weights()) is not None:
        parameters["weights"] = weights_digest(weights)
    settings = {**output_settings(config), "method_parameters": parameters}
    files = [(str(path.resolve()), path.stat().st_size, path.stat().st_mtime_ns) for path in inputs]
    text = json.dumps({"inputs": files, "settings": settings, "version": __version__}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def write_atomically(path: Path, write: Callable[[Path], None]) -> None:
    """Call write(temporary_path) and rename the result to `path`, so `path` is complete or absent."""
    with atomic_output(path) as temporary:
        write(temporary)


@dataclass(frozen=True)
class BucketedPiece:
    """What bucketing a piece tells the run: its occupied grid cells (cells,), their row starts in the stored
    piece (cells+1,), the points of each cell a class rule keeps whole (cells,), and points per class (256,)."""

    cells: np.ndarray
    starts: np.ndarray
    protected: np.ndarray
    classes: np.ndarray


class WorkDir:
    """The work folder of one run, `.<output name>.work-<key>` in the scratch folder."""

    def __init__(self, path: Path) -> None:
        self.path = path

    @classmethod
    def of_run(cls, output: Path, scratch: Path | None, inputs: Sequence[Path], config: RunConfig) -> "WorkDir":
        """The folder of this exact run, whether or not it exists yet."""
        return cls((scratch or output.parent) / f".{output.name}.work-{run_key(inputs, config)}")

    @classmethod
    def for_run(cls, output: Path, scratch: Path | None, inputs: Sequence[Path], config: RunConfig) -> "WorkDir":
        """The folder of this exact run, created with its manifest if it does not exist yet."""
        work = cls.of_run(output, scratch, inputs, config)
        work.create(output, inputs, config)
        return work

    def create(self, output: Path, inputs: Sequence[Path], config: RunConfig) -> None:
        """Make the folder, with its manifest, unless an earlier attempt did."""
        if not (self.path / MANIFEST).is_file():
            self.path.mkdir(parents=True, exist_ok=True)
            manifest = {"key": self.path.name.rsplit("-", 1)[-1], "output": str(output),
                        "inputs": [str(p) for p in inputs], "settings": asdict(config)}
            write_atomically(self.path / MANIFEST, lambda tmp: tmp.write_text(json.dumps(manifest, indent=2)))

    @contextmanager
    def held(self) -> Iterator[None]:
        """Hold the folder for this run (an advisory lock on a file in it, released when the process ends,
        however it ends): a second run of the same command while the first runs, such as an overlapping
        scheduled job, is refused in one line instead of failing on files the first one renames or removes.
        Where the file system has no locks (some network mounts), runs are not held apart."""
        descriptor = os.open(self.path / LOCK, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            if not locked(descriptor):
                raise PipelineError(f"{self.path}: another run of the same command is working in this folder "
                                    "(wait for it to finish, or stop it and re-run to resume)")
            yield
        finally:
            os.close(descriptor)

    def remove_others(self, output: Path) -> list[Path]:
        """Once `output` is written, delete the work folders beside this one of earlier attempts at it with other
        inputs or settings, which no run can resume any more (a changed command starts afresh: each left its
        folder behind, the scan's size uncompressed), but none a run still holds. Returns those removed."""
        removed = []
        for other in sorted(self.path.parent.glob(f".{output.name}.work-*")):
            if other == self.path or not made_for(other, output):  # a shared --scratch holds other outputs' too
                continue
            try:
                descriptor = os.open(other / LOCK, os.O_RDWR | os.O_CREAT, 0o644)
            except OSError:
                continue
            try:
                if locked(descriptor):
                    shutil.rmtree(other, ignore_errors=True)
                    removed.append(other)
            finally:
                os.close(descriptor)
        return removed

    @property
    def store_path(self) -> Path:
        """The bucketed points (tiling.store.TileStore)."""
        return self.path / "tiles"

    def piece_path(self, number: int) -> Path:
        """Where a bucketed piece's occupied cells and row starts are kept once its rows are stored."""
        return self.path / f"piece-{number}.npz"

    def survey_path(self, tile_id: int) -> Path:
        """Where a tile's survey (coverage, and a stratified method's fill loss) is kept."""
        return self.path / f"survey-{tile_id}.npz"

    def cover_path(self, tile_id: int) -> Path:
        """Where a tile counted past its survey's share keeps its farthest point picks and sample."""
        return self.path / f"cover-{tile_id}.npz"

    def tile_path(self, tile_id: int) -> Path:
        """Where a simplified tile's picks are kept."""
        return self.path / f"tile-{tile_id}.npz"

    def finished_piece(self, number: int) -> BucketedPiece | None:
        """A bucketed piece from an earlier attempt, or None."""
        path = self.piece_path(number)
        if not path.is_file():
            return None
        with np.load(path) as saved:
            return BucketedPiece(saved["cells"], saved["starts"], saved["protected"], saved["classes"])

    def save_piece(self, number: int, piece: BucketedPiece) -> None:
        """Record a piece as bucketed (after its rows are in the store)."""
        write_atomically(self.piece_path(number), lambda tmp: save_npz(tmp, **asdict(piece)))

    def drop_damaged(self) -> list[str]:
        """Remove what an earlier attempt left unreadable, so the run makes it again: a result file whose zip
        does not read whole (a file renamed before the disk held it, then a crash or reboot), a stored piece of
        rows whose size is not the one its piece record says (and that record), and every piece record when the
        store's layout file is gone. Resuming assumed that a file that exists is complete: every rerun failed
        alike, in a traceback. Returns the names removed."""
        dropped = [path for path in sorted(self.path.glob("*.npz")) if not whole_zip(path)]
        store = self.store_path
        try:
            row_bytes = TileStore.open(store).row_bytes if TileStore.exists(store) else None
        except (OSError, ValueError, KeyError, TypeError):  # a layout file that does not parse: a new store
            row_bytes = None
            shutil.rmtree(store, ignore_errors=True)
        for record in sorted(self.path.glob("piece-*.npz")):
            if record in dropped:
                continue
            if row_bytes is None:
                dropped.append(record)
                continue
            number = int(record.stem.split("-")[1])
            with np.load(record) as saved:
                expected = int(saved["starts"][-1]) * row_bytes
            rows = [store / array_name(number), store / array_name(number, crowded=True)]
            if (not rows[0].is_file() or rows[0].stat().st_size != expected
                    or rows[1].is_file() and rows[1].stat().st_size % row_bytes):
                dropped.append(record)
        for path in dropped:
            path.unlink(missing_ok=True)
        return [path.name for path in dropped]

    def held_bytes(self) -> int:
        """What the folder holds on disk already (0 if it does not exist): a resumed run needs that much less."""
        return sum(path.stat().st_size for path in self.path.rglob("*") if path.is_file()) if self.path.is_dir() else 0

    def has_results(self) -> bool:
        """Whether any piece, survey or tile finished: worth keeping for a resume."""
        return any(any(self.path.glob(f"{kind}-*.npz")) for kind in ("piece", "survey", "tile"))

    def remove(self) -> None:
        """Delete the folder: the run finished and its output is in place."""
        shutil.rmtree(self.path, ignore_errors=True)


def made_for(folder: Path, output: Path) -> bool:
    """Whether a work folder's manifest names `output` (resolved, as this process sees both)."""
    try:
        named = json.loads((folder / MANIFEST).read_text())["output"]
    except (OSError, ValueError, KeyError, TypeError):
        return False
    return isinstance(named, str) and Path(named).resolve() == output.resolve()


def locked(descriptor: int) -> bool:
    """Take the advisory lock on an open file without waiting: False if another process holds it. True where the
    file system has no locks (some network mounts): runs are then not held apart."""
    try:
        fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        return exc.errno not in (errno.EWOULDBLOCK, errno.EACCES)
    return True


def whole_zip(path: Path) -> bool:
    """Whether an .npz file reads whole: its zip directory and every member's checksum."""
    try:
        with zipfile.ZipFile(path) as archive:
            return archive.testzip() is None
    except (zipfile.BadZipFile, OSError, EOFError):
        return False


def save_npz(path: Path, **arrays: np.ndarray) -> None:
    """np.savez to exactly `path` (given a name, numpy would append .npz)."""
    with open(path, "wb") as file:
        np.savez(file, **arrays)
