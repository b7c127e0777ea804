"""Weights saved whole or not at all: each file written under a temporary name beside its own and renamed only
once every file of the save is written, so a Ctrl-C or a full disk mid-save leaves the earlier weights (and a
.pt and its .npz still a pair), not a truncated file (`train-detail` wrote in place: a stopped save left a
668-byte .pt that torch could not load beside the old .npz)."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Callable, Sequence


def saved_together(writes: Sequence[tuple[Path, Callable[[Path], None]]]) -> None:
    """Call each write(temporary path) for its path, then rename every temporary into place; on any failure
    remove the temporaries and leave the paths as they were."""
    temporaries = [path.with_name(f".{path.name}.tmp-{os.getpid()}") for path, _ in writes]
    try:
        for (path, write), temporary in zip(writes, temporaries):
            path.parent.mkdir(parents=True, exist_ok=True)
            write(temporary)
        for (path, _), temporary in zip(writes, temporaries):
            os.replace(temporary, path)
    except BaseException:
        for temporary in temporaries:
            temporary.unlink(missing_ok=True)
        raise
