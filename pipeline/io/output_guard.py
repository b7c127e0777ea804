"""What a run may write where: never over or into one of its inputs, and `--overwrite` replaces only an
output of the kind the run writes (a LAS/LAZ file, a PLY file, a zarr store), never a stranger's file or folder.

One rule, checked before any work starts, by every command that writes: `run`, `batch` (for all its jobs
at once) and mesh mode. Files are compared as the file system sees them (device and inode), so a
second spelling, a symlink or a hard link of an input is caught as well as the same path.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

from pipeline.errors import PipelineError

SIGNATURES = {".las": b"LASF", ".laz": b"LASF", ".ply": b"ply", ".html": b"<!DOCTYPE html>",  # what a file we write
              ".png": b"\x89PNG", ".pt": b"PK", ".npz": b"PK"}                             # starts with (zips: PK)
ZARR_MARKERS = ("zarr.json", ".zgroup", ".zarray")  # a zarr v3 or v2 store holds one of these at its root


def check_output(output: Path, inputs: Sequence[Path], overwrite: bool, suffixes: Sequence[str]) -> None:
    """Refuse an unsupported suffix, an output that is (or holds) an input, an existing output without
    `overwrite` or one of another kind even with it, and a missing or unwritable output folder."""
    if output.suffix.lower() not in suffixes:
        raise PipelineError(f"{output}: unsupported output type (use {', '.join(suffixes)})")
    for path in inputs:
        if is_same_file(output, path):
            raise PipelineError(f"{output}: is also an input ({path}); write the result under another name "
                                "(--overwrite never replaces an input)")
        if output.is_dir() and is_inside(path, output):
            raise PipelineError(f"{output}: holds the input {path}; replacing it would delete that input")
    if output.exists() or output.is_symlink():
        if not overwrite:
            raise PipelineError(f"{output}: already exists (pass --overwrite to replace it)")
        check_replaceable(output)
    if output.parent.exists() and not output.parent.is_dir():
        raise PipelineError(f"{output.parent}: not a folder, so it cannot hold the output")
    if not output.parent.is_dir():
        raise PipelineError(f"{output.parent}: output folder does not exist")
    if not os.access(output.parent, os.W_OK):
        raise PipelineError(f"{output.parent}: output folder is not writable")


def check_replaceable(output: Path) -> None:
    """An existing output may be replaced only if it is what this run would write there."""
    suffix = output.suffix.lower()
    if suffix == ".zarr":
        if not (output.is_dir() and any((output / marker).is_file() for marker in ZARR_MARKERS)):
            raise PipelineError(f"{output}: exists and is not a zarr store; refusing to replace it "
                                "(move it aside or choose another output name)")
        return
    if not output.is_file():
        raise PipelineError(f"{output}: exists and is not a regular file; refusing to replace it "
                            "(move it aside or choose another output name)")
    signature = SIGNATURES.get(suffix)
    if signature is not None and not starts_with(output, signature):
        raise PipelineError(f"{output}: exists and is not a {suffix[1:].upper()} file; refusing to replace it "
                            "(move it aside or choose another output name)")


def check_distinct_inputs(paths: Sequence[Path]) -> None:
    """Refuse a file given twice (by two spellings, a symlink or a hard link): its points would be read twice."""
    seen: dict[tuple[int, int], Path] = {}
    for path in paths:
        key = file_key(path)
        if key is None:
            continue
        if key in seen:
            raise PipelineError(f"{path}: the same file as {seen[key]}, given twice (its points would be read twice)")
        seen[key] = path


def is_same_file(first: Path, second: Path) -> bool:
    """Whether two names lead to one file (or folder); a missing name is no file."""
    a, b = file_key(first), file_key(second)
    return a is not None and a == b


def is_inside(path: Path, folder: Path) -> bool:
    """Whether `path` resolves to somewhere under `folder`."""
    return Path(os.path.realpath(folder)) in Path(os.path.realpath(path)).parents


def file_key(path: Path) -> tuple[int, int] | None:
    """(device, inode) of what `path` leads to, or None if nothing is there."""
    try:
        status = path.stat()
    except OSError:
        return None
    return status.st_dev, status.st_ino


def starts_with(path: Path, signature: bytes) -> bool:
    """Whether the file's first bytes are `signature` (an unreadable file is not ours to replace)."""
    try:
        with open(path, "rb") as stream:
            return stream.read(len(signature)) == signature
    except OSError:
        return False
