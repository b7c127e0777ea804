"""Worker processes without Dask for an in-process run whose method picks while holding Python's GIL.

Why: fpsample's FPS holds the GIL for the whole of a call (a Python thread beside it got 1 % of its time),
so `fps` tiles on two task threads ran one at a time. Given to worker processes started by a forkserver
(the tasks' modules imported once in the server, each worker forked from it), the pick step ran 1.75x
faster on 2 cores: `fps` on a 6M-point street 11.6-12.3 -> 9.2-9.5 s, on bcts_1..4 (2.83M) 5.0-5.4 ->
4.0-4.3 s, the same bytes. Reading and surveying stay on the run's threads (numpy lets go of the GIL, and
the processes' start then overlaps the reading). Below PROCESS_PICKING_POINTS the start costs what it saves
(a 1M street: no gain); `learned` gained nothing either (its survey already runs 1.5x on two threads).
"""
from __future__ import annotations

import multiprocessing
import threading
from concurrent.futures import Executor, Future, ProcessPoolExecutor
from typing import Any, Callable

from pipeline.engine.tasks import simplify_tile
from pipeline.engine.threads import WORKER_PRELOAD

PROCESS_PICKING_POINTS = 2_000_000  # scans from this size give their picking to worker processes


def picks_in_processes(points: int, threads: int, picks_hold_gil: bool) -> bool:
    """Whether an in-process run of `points` on `threads` task threads sends its tiles' picking to worker
    processes: for a method whose picking holds the GIL, on 2 or more threads, where a forkserver exists."""
    return (picks_hold_gil and threads >= 2 and points >= PROCESS_PICKING_POINTS
            and "forkserver" in multiprocessing.get_all_start_methods())


def picking_processes(workers: int) -> ProcessPoolExecutor:
    """`workers` worker processes forked from a forkserver that has imported the tasks (and ignores Ctrl-C and
    SIGTERM, as its children then do: the run's own process stops them). The server starts at once, on a
    background thread, so its imports overlap the run's reading. Workers inherit the environment as it is
    now: the caller holds BLAS and OpenMP to one thread first."""
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload([WORKER_PRELOAD])
    pool = ProcessPoolExecutor(workers, mp_context=context)
    threading.Thread(target=_start, args=(pool,), name="pipeline-processes-start", daemon=True).start()
    return pool


def _start(pool: ProcessPoolExecutor) -> None:
    """Start the pool's forkserver and first worker (a no-op task); nothing if the run has already ended."""
    try:
        pool.submit(int)
    except RuntimeError:  # shut down before it started
        pass


class PickingElsewhere(Executor):
    """An in-process run's executor: its task threads, but each tile's picking (`picking`, simplify_tile) in
    `workers` worker processes, which `restart` replaces when one has died. Shutting it down waits for both,
    cancelling what has not started."""

    def __init__(self, threads: Executor, workers: int, picking: Callable[..., Any] = simplify_tile) -> None:
        self.threads = threads
        self.workers = workers
        self.picking = picking
        self.processes = picking_processes(workers)

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Future:
        return (self.processes if fn is self.picking else self.threads).submit(fn, *args, **kwargs)

    def restart(self) -> None:
        """Fresh worker processes in place of a pool that lost one (its other tasks failed with it)."""
        self.processes.shutdown(wait=False, cancel_futures=True)
        self.processes = picking_processes(self.workers)

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        self.threads.shutdown(wait, cancel_futures=cancel_futures)
        self.processes.shutdown(wait, cancel_futures=cancel_futures)
