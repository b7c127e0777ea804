"""A bound on stopping: once a run is interrupted, its cluster gets STOP_GRACE_S seconds to close, then
the process ends anyway, with the same one line and exit code.

Why: a Ctrl-C is raised wherever the main thread happens to be, possibly inside Dask's client code while
it holds a lock; the cluster's shutdown then waited for ever (seen once in CI on a loaded machine: no
exit within 300 s). Finished work is on disk in the work folder, written atomically, so ending the
process loses nothing; its workers end with it (Dask's nannies watch their parent).
"""
from __future__ import annotations

import os
import sys
import threading

STOP_GRACE_S = 30.0  # a cluster closes in 0.4-2 s; far longer means it will not


class StopGuard:
    """Armed when a run is interrupted, cancelled once the cluster has closed; if that takes longer than
    `grace_s`, prints `line` on stderr and ends the process with `code` (no clean-up: the work folder stays).
    With `grace_s` None it never arms (a notebook's process is not ours to end)."""

    def __init__(self, grace_s: float | None = STOP_GRACE_S) -> None:
        self.grace_s = grace_s
        self._timer: threading.Timer | None = None

    def arm(self, line: str, code: int) -> None:
        """Start the countdown (a daemon thread: it never holds the process open)."""
        self.cancel()
        if self.grace_s is None:
            return
        self._timer = threading.Timer(self.grace_s, _end_now, args=(line, code))
        self._timer.daemon = True
        self._timer.start()

    def cancel(self) -> None:
        """The cluster closed in time: stop the countdown."""
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None


def _end_now(line: str, code: int) -> None:
    """Print the line and end the process at once, whatever its threads are doing."""
    sys.stderr.write(f"{line}\n")
    sys.stderr.flush()
    os._exit(code)
