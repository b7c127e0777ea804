"""Running tile jobs on Dask: a LocalCluster of single-threaded worker processes by default."""
from __future__ import annotations

import time
from typing import Callable, Sequence

import dask
from dask.distributed import Client, LocalCluster, as_completed
from tqdm import tqdm

from pipeline.errors import PipelineError
from pipeline.tile_task import TileJob, TileOutcome, simplify_tile

ONE_THREAD = {name: "1" for name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")}


def run_jobs(jobs: Sequence[TileJob], workers: int, memory_limit: str, show_progress: bool,
             on_done: Callable[[TileOutcome], None] = lambda outcome: None) -> None:
    """Run every job on a fresh LocalCluster (one thread per worker, BLAS/torch threads 1), tiles largest first."""
    with dask.config.set({"distributed.nanny.pre-spawn-environ": ONE_THREAD,
                          "distributed.worker.daemon": False}):
        with LocalCluster(n_workers=workers, threads_per_worker=1, memory_limit=memory_limit, processes=True,
                          dashboard_address=None) as cluster, Client(cluster) as client:
            _gather(client, jobs, show_progress, on_done)


def _gather(client: Client, jobs: Sequence[TileJob], show_progress: bool,
            on_done: Callable[[TileOutcome], None]) -> None:
    """Submit one task per tile and consume results as they finish, with a tiles and points/s bar."""
    futures = [client.submit(simplify_tile, job, key=f"tile-{job.tile_id}-{job.result_path}", pure=False)
               for job in jobs]
    started, points = time.perf_counter(), 0
    with tqdm(total=len(jobs), unit="tile", disable=not show_progress, desc="simplify") as bar:
        for future in as_completed(futures):
            try:
                outcome = future.result()
            except Exception as exc:
                raise PipelineError(f"a tile task failed: {type(exc).__name__}: {exc}") from exc
            points += outcome.points
            bar.set_postfix_str(f"{points / max(time.perf_counter() - started, 1e-9):,.0f} pts/s")
            bar.update()
            on_done(outcome)
