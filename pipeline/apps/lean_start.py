"""What the command line's process does before its other imports: leave out what a local run never uses,
since a small run's wall time is mostly fixed cost (interpreter, imports, planning)."""
from __future__ import annotations

import sys


def import_laspy_without_http() -> None:
    """Import laspy without its HTTP support for remote COPC files: laspy imports `requests` for it whenever
    that is installed (about 0.1-0.15 s, a fifth of a 110k-point run), and the command line reads local
    files only. `requests` itself stays importable afterwards; only laspy's CopcReader over HTTP is off in
    this process (it then says "HTTP support requires the 'requests' package", which is why). Importing
    pipeline.apps.cli does this; the library (`import pipeline`) does not. Nothing changes where laspy or
    requests is already imported."""
    if "laspy" in sys.modules or "requests" in sys.modules:
        return
    sys.modules["requests"] = None  # type: ignore[assignment]  # laspy's `import requests` fails; it goes on without
    try:
        import laspy  # noqa: F401
    finally:
        del sys.modules["requests"]
