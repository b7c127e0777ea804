"""The one exception type the CLI turns into a single-line message and a non-zero exit, and the warning
that carries a run's notes to Python callers."""
from __future__ import annotations

from pathlib import Path


class PipelineError(Exception):
    """A failure the user can act on: the message names the file and the problem in one line.

    A multi-line message (e.g. a library's error text) is joined with '; ', so the CLI prints one line.
    """

    def __init__(self, message: str) -> None:
        super().__init__("; ".join(line.strip() for line in str(message).splitlines() if line.strip()))


class PipelineNote(UserWarning):
    """Something a run says and goes on (lengths converted or metres assumed, a class with no points, a
    sub-cell over the tile limit): `pipeline run` prints it on stderr, `pipeline.run` warns with it."""


def file_system_error(exc: OSError, path: str | Path | None = None) -> PipelineError:
    """One line naming the file (`path` if given, else the one the system names) and what the system said,
    e.g. 'out.laz: No space left on device'."""
    where = path if path is not None else exc.filename
    reason = exc.strerror or str(exc) or type(exc).__name__
    return PipelineError(f"{where}: {reason}" if where is not None else reason)


def is_fatal_signal(exc: BaseException) -> bool:
    """True for exceptions that must propagate untouched (Ctrl-C, sys.exit), unlike lazrs's PanicException."""
    return isinstance(exc, (KeyboardInterrupt, SystemExit, GeneratorExit))


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread by the CLI's handler, so a run unwinds from it as from Ctrl-C."""


class Interrupted(KeyboardInterrupt):
    """A run stopped by Ctrl-C or SIGTERM, with one line that says what was kept and how to resume; `exit_code`
    is the shell's for the signal (130 for SIGINT, 143 for SIGTERM)."""

    def __init__(self, message: str, exit_code: int) -> None:
        super().__init__(message)
        self.exit_code = exit_code


STOPS: list[KeyboardInterrupt] = []  # the Ctrl-C and SIGTERM this process got, as the CLI's handlers raised them


def raise_if_stopped() -> None:
    """Raise again the Ctrl-C or SIGTERM this process got, if any: a library may have swallowed it (trimesh's
    optional imports catch BaseException) or turned it into an error of its own (see raise_stop_behind)."""
    if STOPS:
        raise type(STOPS[-1])() from None


def raise_stop_behind(error: BaseException) -> None:
    """Raise the Ctrl-C or SIGTERM this process got, if any, in place of `error`: a stop raised in a Python method
    that a native library calls back (lazrs writing or reading through a Python file) comes back as that
    library's error ('IoError: Failed to call write'), which would end the run in a traceback."""
    if not is_fatal_signal(error):
        raise_if_stopped()


def signal_exit_code(exc: KeyboardInterrupt) -> int:
    """130 after Ctrl-C, 143 after SIGTERM (128 + the signal number, as a shell reports it)."""
    return exc.exit_code if isinstance(exc, Interrupted) else 143 if isinstance(exc, Terminated) else 130
