"""Feature-preserving simplification of large LiDAR scans: the Python twin of the `pipeline` command.

`run` simplifies files to a file, `simplify` a cloud in memory to the indices it keeps; `info`,
`evaluate` and `compare` are `pipeline info`, `eval` and `compare`. Heavy modules are imported on first
call, so Dask workers importing `pipeline.engine.tasks` stay light.
"""
from __future__ import annotations

import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

from pipeline.config import RunConfig, build_config, plain_numbers
from pipeline.errors import PipelineError, PipelineNote
from pipeline.version import __version__

if TYPE_CHECKING:
    import laspy
    import numpy as np
    from dask.distributed import Client

    from model.methods import Method
    from pipeline.apps.scoring import Reference, Score
    from pipeline.engine.runner import RunReport

__all__ = ["PipelineError", "PipelineNote", "RunConfig", "__version__", "compare", "evaluate", "info", "run", "simplify"]


def run(inputs: str | Path | Sequence[str | Path], output: str | Path | None = None, *, ratio: float | None = None,
        config: str | None = None, overwrite: bool = False, scratch: str | Path | None = None,
        progress: bool = False, scheduler: str | None = None, client: Client | None = None,
        **settings: Any) -> RunReport:
    """Simplify a scan (one file or several that form one scan) to `output` at `ratio`.

    `config` names a preset (`default`, `toronto3d`, `airborne`) or a TOML file; keyword settings
    (method, tile_size, overlap, workers, memory_limit, seed, levels=(0.2, 0.1), keep_classes=(6,),
    thin_classes=(2,), ...) override it, as CLI flags do; with `levels`, `ratio` may be left out.
    `method` is a name (`"voxel"`) or a simplifier with its parameters (`model.methods.Voxel(slack=0.05)`);
    `method_parameters={"slack": 0.05}` changes the named method's defaults, as a config file's
    `[method.voxel]` table does.
    `progress` shows bars at a terminal, else a line every 10 s on stderr.
    `client` reuses the caller's Dask client (no cluster started); `scheduler` (tcp://host:port) runs on
    an existing Dask cluster; otherwise a scan of at most `in_process_points` (3M at 2 workers; 9M for
    `random`; 21M for `fps`, `voxel` and `learned`, whose tiles go to worker processes from 1M, 2M and 300k points)
    points runs on `workers` threads of this process, and a larger one on a local cluster started for the call.
    What the CLI notes on stderr (lengths converted, metres assumed, ...) comes as a `PipelineNote` warning.
    """
    from pipeline.engine.runner import run_scan
    from pipeline.progress import Progress

    if ratio is None and not plain_numbers(settings.get("levels")):  # an array of levels, too
        raise PipelineError("give ratio (the fraction of points to keep) or levels")
    paths = [inputs] if isinstance(inputs, (str, Path)) else list(inputs)
    return run_scan(paths, output, build_config(config, ratio=ratio, **settings), overwrite=overwrite,
                    scratch=scratch, progress=Progress.for_terminal() if progress else None, scheduler=scheduler,
                    client=client, note=lambda line: warnings.warn(line, PipelineNote, stacklevel=2))


def simplify(points: np.ndarray | laspy.LasData, ratio: float, *, method: str | Method = "learned",
             config: str | None = None, client: Client | None = None, **settings: Any) -> np.ndarray:
    """Indices of the points of an (n, 3) array or a `laspy.LasData` to keep, most important first
    (see pipeline.apps.in_memory.simplify): tiles, budgets and seams as `run` on the same points."""
    from pipeline.apps.in_memory import simplify as simplify_cloud

    return simplify_cloud(points, ratio, method=method, config=config, client=client, **settings)


def info(path: str | Path, count_points: bool = True) -> dict[str, Any]:
    """`pipeline info`: header, CRS with EPSG and units, density, size, class and return counts of a file."""
    from pipeline.apps.scan_summary import summarize

    return summarize(path, count_points)


def evaluate(reference: str | Path, candidates: Sequence[str | Path], sample: int = 200_000,
             seed: int = 0) -> tuple[Reference, list[Score]]:
    """`pipeline eval`: every quality metric of each candidate against the reference (on `sample`
    reference points in whole grid cells; 0: every point); Hausdorff in `Reference.unit`, CD (mean squared distances) in its square."""
    from pipeline.apps.scoring import evaluate as evaluate_files

    return evaluate_files(Path(reference), [Path(c) for c in listed(candidates, (str, Path))], sample, seed)


def compare(source: str | Path, ratios: Sequence[float] = (0.2, 0.1, 0.05),
            methods: Sequence[str] = ("learned", "fps", "voxel", "random", "tcp"), out_dir: str | Path = "compare",
            workers: int = 2, sample: int = 200_000, seed: int = 0) -> list[Path]:
    """`pipeline compare`: simplify `source` with each method at each ratio, score them, and write the
    table, JSON, plots and pictures to `out_dir`; return the files written."""
    from pipeline.apps.comparison import RunOptions, compare as compare_methods

    return compare_methods(Path(source), listed(ratios, (int, float, str)), listed(methods, (str,)), Path(out_dir),
                           RunOptions(workers=workers, seed=seed), sample)


def listed(values: Any, single: tuple[type, ...]) -> list[Any]:
    """A sequence argument as a list; one value of a `single` type (a path, a ratio, a method name) as a list of
    it, not of its characters."""
    return [values] if isinstance(values, single) else list(values)
