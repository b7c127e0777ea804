"""Threads and cores: how many workers this machine can run, and running tasks on threads of this process
with one thread each for BLAS, OpenMP and torch, as a Dask worker does."""
from __future__ import annotations

import os
import sys
from concurrent.futures import Executor, ThreadPoolExecutor
from contextlib import contextmanager
from typing import Iterator

from threadpoolctl import threadpool_limits

ONE_THREAD = {name: "1" for name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")}


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity, which containers and Slurm narrow)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def local_workers(requested: int) -> int:
    """Worker processes for a local cluster: as requested, but no more than the cores (more only contend
    for them and multiply memory; `--workers 1000` would start a thousand processes)."""
    return max(1, min(requested, available_cores()))


LIGHT_ON_GIL_SCALE = 3  # how many times more points a method light on the GIL runs in-process: with 2 workers
# threads and a cluster tied at about 10M points for `fps` (street, 54.6 s and 54.4 s) and about 4M for `learned`
# (street, 39.3 and 37.7 s); `voxel` won on threads at 10M (36.6 s against 43.4) before its tiles went to processes


TILE_PROCESS_SCALE = 7  # how many times more points run in-process when the tiles' surveys and picks go to worker
# processes (pipeline.engine.processes), where the GIL no longer holds them back: on a 2-core machine that beat a
# local cluster on the street in time and memory at every size measured, up to 20M (`learned` at 6M 13.9-14.2 s and
# 391-411 MiB against 16.3-17.0 s and 462-469 MiB, at 20M 48.1 s / 408 against 53.8 / 482; `fps` at 20M 19.9 s /
# 347 against 25.5 / 443; `voxel` at 10M 10.5 s / 380 against 15.3 / 411, and 11.0-11.2 / 229 on threads). Larger
# scans keep a local cluster, whose workers' memory limit then matters most.


def runs_in_process(points: int, limit: int, threads: int, light_on_gil: bool = False,
                    tile_processes: bool = False) -> bool:
    """Whether a scan of `points` runs on `threads` threads of this process rather than on a local cluster:
    up to `limit` points at 2 threads, where it was measured, fewer with more; LIGHT_ON_GIL_SCALE times more
    for a method whose work lets go of Python's GIL, TILE_PROCESS_SCALE times more where its tiles go to
    worker processes (`tile_processes`). A task holds the GIL for a share of its time (bench/gil_share.py),
    so threads lose to processes in proportion to 1 - 1/threads (Amdahl's law), while the cluster's start
    and close stay the same."""
    scale = TILE_PROCESS_SCALE if tile_processes else LIGHT_ON_GIL_SCALE if light_on_gil else 1
    return points <= limit * scale * 0.5 / (1 - 1 / max(threads, 2))


def one_openmp_thread() -> None:
    """Hold OpenMP (pykdtree's kNN) to one thread in the calling thread. The in-process run's own limit does
    not reach its task threads: OpenMP's thread count is set per thread, and a new thread starts from the
    process default (every core), so each task's kNN ran on both cores of 2, one worker using two of them
    (measured: a 200k-point k=16 query on a task thread took 0.5 s wall for 1.0 s of CPU, 1.4 s on the
    limited main thread)."""
    threadpool_limits(limits=1, user_api="openmp")


@contextmanager
def in_process(threads: int = 1, tile_processes: bool = False) -> Iterator[Executor]:
    """A pool of `threads` task threads in this process, BLAS, OpenMP and torch held to one thread each as
    in a worker, so the output equals a cluster run's byte for byte; they are given back afterwards. With
    `tile_processes`, the tiles' surveys and picks go to as many worker processes instead
    (pipeline.engine.processes: for a method whose tile work holds the GIL a fair share).

    Leaving it (also on an error or Ctrl-C) cancels the tasks not started and waits for the running ones:
    at most one tile each, and none writes after the run has said what it kept."""
    saved = {name: os.environ.get(name) for name in ONE_THREAD}
    os.environ.update(ONE_THREAD)  # read by torch if a task imports it for the first time
    torch = sys.modules.get("torch")
    torch_threads = torch.get_num_threads() if torch is not None else available_cores()
    if torch is not None:
        torch.set_num_threads(1)
    try:
        with threadpool_limits(limits=1), ThreadPoolExecutor(threads, thread_name_prefix="pipeline-task",
                                                            initializer=one_openmp_thread) as pool:
            executor: Executor = pool
            if tile_processes:
                from pipeline.engine.processes import TilesElsewhere

                executor = TilesElsewhere(pool, threads)
            try:
                yield executor
            finally:
                executor.shutdown(cancel_futures=True)
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value
        if "torch" in sys.modules:
            sys.modules["torch"].set_num_threads(torch_threads)
