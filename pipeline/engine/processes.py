"""Worker processes without Dask for an in-process run whose method picks while holding Python's GIL.

Why: fpsample's FPS holds the GIL for the whole of a call (a Python thread beside it got 1 % of its time),
so `fps` tiles on two task threads ran one at a time. Given to worker processes forked from a forkserver
(the tasks' modules imported once in the server), the pick step ran 1.75x faster on 2 cores: `fps` on a
6M-point street 10.7-12.3 -> 9.0-9.1 s, on bcts_1..4 (2.83M) 5.3-5.6 -> 4.3-4.8 s, the same bytes. Reading
and surveying stay on the run's threads (numpy lets go of the GIL there). Below PROCESS_PICKING_POINTS the
processes cost what they save (a 1M street: no gain); `learned` gained nothing either (its survey already
runs 1.5x on two threads).
"""
from __future__ import annotations

import ctypes
import multiprocessing
import os
import signal
import threading
from collections.abc import Iterator
from concurrent.futures import Executor, Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from multiprocessing import forkserver
from typing import Any, Callable

from threadpoolctl import threadpool_limits

from pipeline.engine.allocator import map_large_arrays
from pipeline.engine.tasks import simplify_tile

PROCESS_PICKING_POINTS = 2_000_000  # scans from this size give their picking to worker processes
SERVER_PRELOAD = "pipeline.engine.picking_server"  # the forkserver imports the tasks once
PR_SET_PDEATHSIG = 1  # Linux's prctl option: a signal this process gets when its parent ends


def picks_in_processes(points: int, threads: int, picks_hold_gil: bool) -> bool:
    """Whether an in-process run of `points` on `threads` task threads sends its tiles' picking to worker
    processes: for a method whose picking holds the GIL, on 2 or more threads, where a forkserver exists."""
    return (picks_hold_gil and threads >= 2 and points >= PROCESS_PICKING_POINTS
            and "forkserver" in multiprocessing.get_all_start_methods())


def importing_parents_script() -> bool:
    """Whether this process is a worker (a picking process, a local Dask worker) still importing the script
    that started it (multiprocessing's own flag, which its checks read): a run started there would be a
    second run of the same files, into the same work folder."""
    return bool(getattr(multiprocessing.current_process(), "_inheriting", False))


def picking_processes(workers: int) -> ProcessPoolExecutor:
    """`workers` worker processes forked from the forkserver, started now (a fork and exec: its imports, in
    pipeline.engine.picking_server, run in it while the run reads, Ctrl-C ignored). Each worker sets itself
    up as a Dask worker is (setup_worker): Ctrl-C and SIGTERM are the run's own process's, which stops the
    pool."""
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload([SERVER_PRELOAD])
    with ctrl_c_ignored():
        forkserver.ensure_running()
    return ProcessPoolExecutor(workers, mp_context=context, initializer=setup_worker)


@contextmanager
def ctrl_c_ignored() -> Iterator[None]:
    """SIGINT ignored for a moment (from the main thread only, which alone may set handlers): a process
    started meanwhile keeps it ignored through exec, until pipeline.engine.picking_server hands it back."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def setup_worker() -> None:
    """A picking process as it starts, whoever started the forkserver: Ctrl-C and SIGTERM ignored, ended with
    the run's process (through the server), BLAS and OpenMP on one thread, large arrays mapped whole."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    let_server_end()
    die_with_parent()
    threadpool_limits(limits=1)
    map_large_arrays()


def let_server_end() -> None:
    """Close this worker's copy of the forkserver's keep-alive pipe: multiprocessing hands one to every child
    it forks (a child may fork in turn), so the server outlived a killed run while its workers lived, and
    they, waiting on their queues, for ever (seen: a SIGKILLed run left both). Without it, the server ends
    when the run's process does, and the workers with it (die_with_parent)."""
    server = getattr(forkserver, "_forkserver", None)
    alive = getattr(server, "_forkserver_alive_fd", None)
    if alive is not None:
        os.close(alive)
        server._forkserver_alive_fd = None


def die_with_parent() -> None:
    """Have Linux kill this process when its parent ends (prctl's parent-death signal); nothing elsewhere."""
    try:
        prctl = ctypes.CDLL(None).prctl
    except (OSError, AttributeError):
        return
    parent = os.getppid()
    prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL))
    if os.getppid() != parent:  # it ended before the request took
        os._exit(1)


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
        """The call's future; a pool already broken gives one failed with BrokenProcessPool, as its running
        tasks' are, so the caller restarts it in one place."""
        if fn is not self.picking:
            return self.threads.submit(fn, *args, **kwargs)
        try:
            return self.processes.submit(fn, *args, **kwargs)
        except BrokenProcessPool as exc:
            failed: Future = Future()
            failed.set_exception(exc)
            return failed

    def restart(self) -> None:
        """Fresh worker processes in place of a pool that lost one (its other tasks failed with it)."""
        self.processes.shutdown(wait=False, cancel_futures=True)
        self.processes = picking_processes(self.workers)

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        self.threads.shutdown(wait, cancel_futures=cancel_futures)
        self.processes.shutdown(wait, cancel_futures=cancel_futures)
