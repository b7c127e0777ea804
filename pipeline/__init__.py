"""Feature-preserving simplification of large LiDAR scans; `pipeline.run(...)` mirrors `pipeline run`."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

from typing import TYPE_CHECKING

from pipeline.config import RunConfig, build_config
from pipeline.errors import PipelineError

if TYPE_CHECKING:
    from pipeline.runner import RunReport

__all__ = ["PipelineError", "RunConfig", "run"]


def run(inputs: str | Path | Sequence[str | Path], output: str | Path | None = None, *, ratio: float | None = None,
        config: str | None = None, overwrite: bool = False, scratch: str | Path | None = None,
        progress: bool = False, scheduler: str | None = None, **settings: Any) -> "RunReport":
    """Simplify a scan (one file or several that form one scan) to `output` at `ratio`.

    `config` names a preset (`default`, `toronto3d`, `airborne`) or a TOML file; keyword settings
    (method, tile_size, overlap, workers, memory_limit, seed, levels=(0.2, 0.1), keep_classes=(6,),
    thin_classes=(2,), ...) override it, as CLI flags do; with `levels`, `ratio` may be left out.
    `scheduler` (tcp://host:port) runs on an existing Dask cluster instead of a local one.
    """
    from pipeline.runner import run_scan  # imported here so Dask workers importing pipeline.tasks stay light

    if ratio is None and not settings.get("levels"):
        raise PipelineError("give ratio (the fraction of points to keep) or levels")
    paths = [inputs] if isinstance(inputs, (str, Path)) else list(inputs)
    return run_scan(paths, output, build_config(config, ratio=ratio, **settings), overwrite=overwrite,
                    scratch=scratch, show_progress=progress, scheduler=scheduler)
