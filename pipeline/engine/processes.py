"""Worker processes without Dask for an in-process run whose tile work holds Python's GIL a fair share.

Why: fpsample's FPS holds the GIL for the whole of a call (a Python thread beside it got 1 % of its time),
so `fps` tiles on two task threads ran one at a time. Given to worker processes forked from a forkserver
(the tasks' modules imported once in the server), the pick step ran 1.75x faster on 2 cores: `fps` on a
6M-point street 10.7-12.3 -> 9.0-9.1 s, on bcts_1..4 (2.83M) 5.3-5.6 -> 4.3-4.8 s, the same bytes.

The survey goes there too, and so do the fill's (`learned`'s) tiles: on two threads its surveys and picks
ran 1.76x and 1.42x one thread's speed, their CPU time inflated by 5 and 14 % and 0.5-0.6 s spent waiting
for the GIL (the hole cover's Python loop, numpy's many calls on 31k-point bcts tiles). In processes, on
bcts_1..4 the simplify phase ran `learned` 5.75-5.82 -> 5.01-5.10 s (wall 7.2-7.5 -> 6.5-6.8 s under a
memory probe) and `fps` 1.48-1.57 -> 1.40-1.46 s; `learned` on a 2.8M street 5.97-6.27 -> 5.08-5.15 s, on
a 1.5M one 3.3 -> 2.8-2.9 s. The run's tree then peaks about twice as high (bcts `learned` 176-208 -> 395
MiB, about a local cluster's), with the same bytes. `voxel` then gained 3 % (its simplify phase 1.23 -> 0.98 s,
its reading 0.2 s slower) for twice the memory; measured again at 0.3.10 (2 cores, alternated, wall s, threads ->
processes), it gains from about 2M points: bcts_1..4 as PLY 2.98-3.06 -> 2.56-2.64 (simplify phase 1.78 ->
1.32-1.38), a 10M street 10.95-11.18 -> 10.48-10.50 (229 -> 380 MiB); a 2M street 2.17-2.38 -> 2.22-2.36 (a tie),
a 1M one 1.32-1.38 -> 1.47-1.55, the extra-bytes file's 698k a tie, lone-star's 519k 0.06 s slower.
`random` lost (1.38-1.40 -> 1.48-1.60 s): its tiles stay on threads. Reading stays on the run's threads (lazrs
decodes on every core). Below a method's `tile_processes_from` the forkserver's start, which competes with the
reading, costs what the processes save: with the server importing only what tiles need (139 ms; 245 with the
scan reader), a 1M street ran `fps` 1.33-1.41 -> 1.19-1.24 s and `learned` 2.68-2.76 -> 2.56-2.68 s in
processes, and the tree peaks higher (the 1M street's `learned` 186-228 -> 377 MiB). `fps` gains nothing below
that (0.3.9, 2 cores, wall s, threads -> processes: lone-star's 519k 0.78-0.81 -> 0.83-0.88, the extra-bytes
file's 698k 0.89-0.94 -> 0.91-1.04), but the fill family's tiles, whose hole cover and survey have grown, do
from about 300k points: `learned` on lone-star 1.59-1.69 -> 1.50-1.52, bcts_1's 532k 1.37-1.38 -> 1.32-1.34, the
extra-bytes file 1.70-1.76 -> 1.56-1.65, three lone-star pieces' 410k 1.80-1.82 -> 1.68-1.72, two pieces' 277k
1.33-1.39 -> 1.32-1.36 (a tie; `stratified` 0.96-1.02 either way), one piece's 155k 0.86-0.91 -> 0.96-0.98 and
autzen's 110k 0.55 -> 0.64.
"""
from __future__ import annotations

import ctypes
import multiprocessing
import os
import pickle
import signal
import tempfile
import threading
from collections.abc import Iterator
from concurrent.futures import Executor, Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from functools import lru_cache
from multiprocessing import forkserver
from typing import Any, Callable

from threadpoolctl import threadpool_limits

from pipeline.engine.allocator import map_large_arrays
from pipeline.engine.tasks import count_cover, simplify_tile, survey_tile

SERVER_PRELOAD = "pipeline.engine.tile_server"  # the forkserver imports the tasks once
PR_SET_PDEATHSIG = 1  # Linux's prctl option: a signal this process gets when its parent ends


def use_tile_processes(points: int, threads: int, processes_from: int | None) -> bool:
    """Whether an in-process run of `points` on `threads` task threads sends its tiles' surveys and picks to
    worker processes: from the method's `processes_from` points (Method.tile_processes_from; None: never),
    on 2 or more threads, where a forkserver exists."""
    return (processes_from is not None and threads >= 2 and points >= processes_from
            and "forkserver" in multiprocessing.get_all_start_methods())


def importing_parents_script() -> bool:
    """Whether this process is a worker (a tile process, a local Dask worker) still importing the script
    that started it (multiprocessing's own flag, which its checks read): a run started there would be a
    second run of the same files, into the same work folder."""
    return bool(getattr(multiprocessing.current_process(), "_inheriting", False))


def tile_processes(workers: int) -> ProcessPoolExecutor:
    """`workers` worker processes forked from the forkserver, started now (a fork and exec: its imports, in
    pipeline.engine.tile_server, run in it while the run reads, Ctrl-C ignored). Each worker sets itself
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
    started meanwhile keeps it ignored through exec, until pipeline.engine.tile_server hands it back."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def setup_worker() -> None:
    """A tile process as it starts, whoever started the forkserver: Ctrl-C and SIGTERM ignored, ended with
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


class SentOnce:
    """A value that every task of a phase takes (the tile plan), pickled once to a file: a task sent to a tile
    process carries the file's path, and each process reads the value from it once (read_once). Sent with
    every task instead, bcts_1..4's 68 KB plan was pickled, piped and unpickled 91 times a phase (seven
    copies of it, 19.8M points: 75 KB, 256 times); the tasks grow in number with the scan."""

    def __init__(self, value: Any, path: str) -> None:
        self.value = value  # this process's own, for the tasks its threads run
        self.path = path

    def __reduce__(self) -> tuple[Callable[[str], Any], tuple[str]]:
        return read_once, (self.path,)


@lru_cache(maxsize=4)
def read_once(path: str) -> Any:
    """The value a SentOnce wrote to `path`, read once in each process (each run's files have new paths)."""
    with open(path, "rb") as file:
        return pickle.load(file)


class TilesElsewhere(Executor):
    """An in-process run's executor: its task threads, but each tile's survey, cover count and picks
    (`tile_work`: survey_tile, count_cover, simplify_tile) in `workers` worker processes, which `restart`
    replaces when one has died. Shutting it down waits for both, cancelling what has not started, and
    removes the SentOnce files."""

    def __init__(self, threads: Executor, workers: int,
                 tile_work: tuple[Callable[..., Any], ...] = (survey_tile, count_cover, simplify_tile)) -> None:
        self.threads = threads
        self.workers = workers
        self.tile_work = tile_work
        self.processes = tile_processes(workers)
        self.folder: tempfile.TemporaryDirectory[str] | None = None  # the SentOnce files' folder, made once needed
        self.sent: dict[int, SentOnce] = {}  # by id of the value, which each SentOnce keeps alive

    def shared(self, function: Callable[..., Any], values: tuple[Any, ...]) -> tuple[Any, ...]:
        """The arguments that every call of `function` takes after its item, as this executor sends them:
        as SentOnce files where `function` is tile work, as they are where it runs on the threads."""
        return tuple(self._sent_once(value) for value in values) if function in self.tile_work else values

    def _sent_once(self, value: Any) -> SentOnce:
        """The value's SentOnce, its file written the first time the value is shared."""
        if id(value) not in self.sent:
            if self.folder is None:
                self.folder = tempfile.TemporaryDirectory(prefix="pipeline-shared-")
            path = os.path.join(self.folder.name, f"{len(self.sent)}.pickle")
            with open(path, "wb") as file:
                pickle.dump(value, file, protocol=pickle.HIGHEST_PROTOCOL)
            self.sent[id(value)] = SentOnce(value, path)
        return self.sent[id(value)]

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Future:
        """The call's future; a pool already broken gives one failed with BrokenProcessPool, as its running
        tasks' are, so the caller restarts it in one place."""
        if fn not in self.tile_work:
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
        self.processes = tile_processes(self.workers)

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        self.threads.shutdown(wait, cancel_futures=cancel_futures)
        self.processes.shutdown(wait, cancel_futures=cancel_futures)
        if self.folder is not None:
            self.folder.cleanup()
