"""Dask clusters for a run: a LocalCluster of single-threaded worker processes, or an existing scheduler
reached over TCP; imported only when a run needs one (dask.distributed takes 0.3 s to import)."""
from __future__ import annotations

import logging
import os
import socket
import traceback
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Iterator
from urllib.parse import urlsplit

import dask
from dask.distributed import Client, LocalCluster, WorkerPlugin

from pipeline.engine.allocator import map_large_arrays
from pipeline.engine import worker_watch
from pipeline.engine.threads import ONE_THREAD, local_workers
from pipeline.errors import PipelineError

# imported as each worker starts: the tasks, and signals left to the run
WORKER_PRELOAD = "pipeline.engine.worker_setup"


@contextmanager
def local_cluster(workers: int, memory_limit: str) -> Iterator[Client]:
    """A client on a fresh LocalCluster: `workers` processes (capped at the cores), one thread each,
    BLAS/torch threads 1.

    Workers are spawned (Dask's default): forking started them 1.3 s faster, but a forked child can
    inherit a lock held by one of the parent's threads, and in a long-lived process (the test suite)
    a worker hung that way. Starting the cluster in a background thread, to overlap the client's own
    imports, gained nothing measurable on 2 cores, so it starts here, in line.
    """
    quiet_dask_logs()
    # Not Dask's MALLOC_TRIM_THRESHOLD_=65536: trimming cut fps peak RSS on a 4M scan from 1.22 to 0.89 GB
    # but made read+bucket 1.6x and simplify 1.5x slower on bcts_1..4 (page faults on every big array).
    # Dask's statistical profiler samples each worker's threads every 10 ms for a dashboard we never start:
    # off, the workers of a learned run on bcts_1..4 used 6 % less CPU.
    with dask.config.set({"distributed.nanny.pre-spawn-environ": ONE_THREAD, "distributed.worker.profile.enabled": False}), \
            ExitStack() as opened:
        with workers_started():
            cluster = opened.enter_context(LocalCluster(
                n_workers=local_workers(workers), threads_per_worker=1, memory_limit=memory_limit, processes=True,
                dashboard_address=None, preload=[WORKER_PRELOAD],
                # no dashboard; the scheduler's health-check server takes a free port, not 8787,
                # which another run may hold (Dask then warns on stderr, breaking one-line errors)
                scheduler_kwargs={"dashboard_address": "127.0.0.1:0"}))
        client = opened.enter_context(Client(cluster))
        client.register_plugin(WorkerSettings())
        yield client


@contextmanager
def workers_started() -> Iterator[None]:
    """A local cluster whose workers fail to start ends in one line: most often a script that runs the tool at
    its top level, which each spawned worker imports again (Dask said only 'Nanny failed to start', after the
    workers' tracebacks)."""
    try:
        yield
    except RuntimeError as exc:
        if "failed to start" not in str(exc):
            raise
        raise PipelineError(f"the local Dask cluster's workers failed to start ({exc}): a script that calls "
                            "pipeline.run or pipeline.compare must do so under `if __name__ == \"__main__\":`, "
                            "as each worker imports it again") from None


@contextmanager
def connect(scheduler: str, connect_s: float = 10.0) -> Iterator[Client]:
    """A client on an existing dask.distributed cluster at `scheduler` (tcp://host:port) with a worker within
    WORKER_WAIT_S.

    Its workers must import this package and see the inputs and the scratch folder at the same paths.
    """
    quiet_dask_logs()
    probe_scheduler(scheduler, connect_s)
    try:
        client = Client(scheduler, timeout=f"{connect_s}s")
    except (OSError, TimeoutError, ValueError) as exc:
        raise PipelineError(f"{scheduler}: cannot reach the Dask scheduler ({exc})") from exc
    with client:
        try:
            client.wait_for_workers(1, timeout=worker_watch.WORKER_WAIT_S)
        except TimeoutError as exc:
            raise PipelineError(f"{scheduler}: the Dask scheduler has no workers") from exc
        client.register_plugin(WorkerSettings())
        yield client


HANDSHAKE_MAX_BYTES = 2**24  # a Dask scheduler's greeting is a few hundred bytes; "HTTP/1.1" read as a length is ~10^18


def probe_scheduler(scheduler: str, timeout_s: float) -> None:
    """Refuse, in one line and within `timeout_s`, a tcp:// address where nothing listens, or where what
    listens is not a Dask scheduler: a scheduler greets every new connection first (the length of its
    handshake message, 8 bytes little-endian, then the message), so silence or an absurd length means
    another service (Dask's own client would wait for ever or try to allocate exabytes)."""
    address = urlsplit(scheduler if "://" in scheduler else f"tcp://{scheduler}")
    if address.scheme != "tcp":
        return  # tls:// and others: left to Dask's own connection checks
    try:
        port = address.port
    except ValueError:
        port = None
    if address.hostname is None or port is None:
        raise PipelineError(f"{scheduler}: a scheduler address looks like tcp://HOST:PORT")
    try:
        with socket.create_connection((address.hostname, port), timeout=timeout_s) as connection:
            connection.settimeout(timeout_s)
            greeting = b""
            while len(greeting) < 8:
                chunk = connection.recv(8 - len(greeting))
                if not chunk:
                    raise PipelineError(f"{scheduler}: the service there closed the connection without a Dask "
                                        "handshake (not a Dask scheduler?)")
                greeting += chunk
    except TimeoutError:
        raise PipelineError(f"{scheduler}: no Dask handshake within {timeout_s:g} s (nothing answers there, or it "
                            "is not a Dask scheduler)") from None
    except OSError as exc:
        raise PipelineError(f"{scheduler}: cannot reach the Dask scheduler ({exc.strerror or exc})") from None
    if not 0 < int.from_bytes(greeting, "little") <= HANDSHAKE_MAX_BYTES:
        raise PipelineError(f"{scheduler}: the service there does not speak Dask's protocol (not a Dask scheduler)")


def quiet_dask_logs() -> None:
    """Keep Dask's own logs to real errors: a failed task is reported once, by us, as one line."""
    tornado_errors = logging.getLogger("tornado.application")
    if not any(isinstance(each, SyncCancelRace) for each in tornado_errors.filters):
        tornado_errors.addFilter(SyncCancelRace())
    logging.getLogger("distributed").setLevel(logging.ERROR)
    logging.getLogger("distributed.gc").setLevel(logging.ERROR)  # Dask's config sets it to WARNING by name
    # the client's warnings ("Couldn't gather 1 keys, rescheduling": a worker died mid-fetch) and errors (a
    # lost scheduler's reconnect traceback): the run reports the failure itself, in one line
    logging.getLogger("distributed.client").setLevel(logging.CRITICAL)
    logging.getLogger("distributed.worker").setLevel(logging.CRITICAL)
    logging.getLogger("distributed.scheduler").setLevel(logging.CRITICAL)  # "N workers died running task X": map_tasks says it


class SyncCancelRace(logging.Filter):
    """Drops the NameError traceback that distributed (2026.8.0) logs when Ctrl-C or SIGTERM lands in a
    blocking client call before its coroutine has started: `sync`'s `cancel` callback then reads a
    variable not yet bound. There was nothing to cancel yet and the run unwinds and closes the cluster
    anyway, but the traceback would break the one-line message a stopped run prints."""

    def filter(self, record: logging.LogRecord) -> bool:
        error = record.exc_info[1] if record.exc_info else None
        if not isinstance(error, NameError) or error.__traceback__ is None:
            return True
        last = traceback.extract_tb(error.__traceback__)[-1]
        return not (last.name == "cancel" and Path(last.filename).parts[-2:] == ("distributed", "utils.py"))


class WorkerSettings(WorkerPlugin):
    """Applied in every worker process, including ones started after a worker dies or joins later:
    quiet_dask_logs, large arrays mapped whole (pipeline.engine.allocator), so memory stays flat over a run,
    and lazrs's chunk-parallel LAZ decoding (pipeline.io.las_source.LasSource.read) held to one thread unless
    the worker's environment says otherwise: a worker runs one thread, and its peers decode beside it."""

    def setup(self, worker: object) -> None:
        quiet_dask_logs()
        map_large_arrays()
        os.environ.setdefault("RAYON_NUM_THREADS", "1")  # read when lazrs first decodes in parallel
