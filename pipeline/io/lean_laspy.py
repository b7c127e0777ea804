"""What the command line's process and the tile processes' server do before their other imports: leave out
what a local run never uses, since a small run's wall time is mostly fixed cost (interpreter, imports,
planning)."""
from __future__ import annotations

import sys

LEFT_OUT = ("requests", "pyproj")  # what laspy imports at its own import if installed, and a run may not need


def import_laspy_lean() -> None:
    """Import laspy without the optional packages it imports up front whenever they are installed:

    - `requests`, for its HTTP support for remote COPC files (about 0.1-0.15 s, a fifth of a 110k-point run),
      which the command line never uses (local files only): laspy's CopcReader over HTTP is off in this
      process (it then says "HTTP support requires the 'requests' package", which is why);
    - `pyproj` (70-90 ms with the urllib, email and certifi modules it brings), which laspy's CRS parsing
      imports again when it runs: a scan with a CRS still has it parsed (pipeline.io.crs), one without
      (a Toronto3D PLY) never pays for it.

    Both stay importable afterwards. Importing pipeline.apps.cli or pipeline.engine.tile_server does this;
    the library (`import pipeline`) does not. Nothing changes where laspy or one of them is already imported."""
    if "laspy" in sys.modules or any(name in sys.modules for name in LEFT_OUT):
        return
    for name in LEFT_OUT:
        sys.modules[name] = None  # type: ignore[assignment]  # laspy's `import name` fails; it goes on without
    try:
        import laspy  # noqa: F401
    finally:
        for name in LEFT_OUT:
            del sys.modules[name]
