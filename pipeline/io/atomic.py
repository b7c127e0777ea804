"""Write-then-rename, so a failed or killed run never leaves a half-written file under the final name."""
from __future__ import annotations

import os
import shutil
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    elif path.exists() or path.is_symlink():
        path.unlink()


SETTLE_S = (0.02, 0.05, 0.1, 0.2, 0.4)  # waits after a failed write's removal, for writes still in flight


def _removed_again_if_back(path: Path) -> None:
    """Remove a failed store's folder again if it comes back within about a second: when one chunk write of
    a zarr store fails (a full disk), zarr's asyncio.gather raises at once while its event loop thread goes
    on with the chunks already in flight, and one that lands after the removal recreates the folder (seen
    once under load: a `.out.zarr.tmp-PID` left behind on a full disk)."""
    for wait in SETTLE_S:
        time.sleep(wait)
        if path.exists() or path.is_symlink():
            _remove(path)


@contextmanager
def atomic_output(final: Path) -> Iterator[Path]:
    """Yield a hidden temporary path beside `final`; on success it replaces `final`, on error it is removed."""
    temporary = final.parent / f".{final.name}.tmp-{os.getpid()}"
    _remove(temporary)
    try:
        yield temporary
        if final.is_dir() and not final.is_symlink():
            # a directory (zarr store) cannot be replaced in one step: move the old one aside first
            old = final.parent / f".{final.name}.old-{os.getpid()}"
            os.replace(final, old)
            os.replace(temporary, final)
            _remove(old)
        else:
            os.replace(temporary, final)
    except BaseException:
        store = temporary.is_dir() and not temporary.is_symlink()
        _remove(temporary)
        if store:
            _removed_again_if_back(temporary)
        raise


def remove_stale_temporaries(final: Path) -> None:
    """Delete temporaries of `final` left by runs that were killed (their process is gone)."""
    for pattern in (f".{final.name}.tmp-*", f".{final.name}.old-*"):
        for leftover in final.parent.glob(pattern):
            pid = leftover.name.rsplit("-", 1)[-1]
            if pid.isdigit() and not _alive(int(pid)):
                _remove(leftover)


def _alive(pid: int) -> bool:
    """Whether a process with this id exists (a permission error means it does)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
