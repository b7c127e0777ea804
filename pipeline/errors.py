"""The one exception type the CLI turns into a single-line message and a non-zero exit."""


class PipelineError(Exception):
    """A failure the user can act on: the message names the file and the problem in one line."""


def is_fatal_signal(exc: BaseException) -> bool:
    """True for exceptions that must propagate untouched (Ctrl-C, sys.exit), unlike lazrs's PanicException."""
    return isinstance(exc, (KeyboardInterrupt, SystemExit, GeneratorExit))
