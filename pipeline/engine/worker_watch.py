"""A run on a Dask cluster whose workers have all gone: Dask waits for new ones for ever (an existing cluster's
`dask worker` processes killed, a local cluster's nannies killed), which would hang a scheduled job. WorkerWatch
ends the wait after WORKER_WAIT_S and says why; the run keeps its finished tiles for a resume."""
from __future__ import annotations

import threading
import time
from typing import TYPE_CHECKING, Any, Callable

from pipeline.errors import PipelineError

if TYPE_CHECKING:
    from dask.distributed import Client

WORKER_WAIT_S = 60.0  # how long a run waits for a worker: on connecting to a scheduler, and mid-run once all are gone
POLL_S = 1.0  # how often the scheduler is asked for its workers (one round trip)


class WorkerWatch:
    """While open, asks the scheduler every `poll_s` how many worker threads it has. Once it has had none for
    `wait_s`, cancels `futures()` (the blocked client calls then return) and `fired` is set: `error` is the
    run's one line. A scheduler that cannot answer is left to the client, which reports a lost scheduler."""

    def __init__(self, client: Client, futures: Callable[[], list[Any]], desc: str,
                 wait_s: float | None = None, poll_s: float = POLL_S) -> None:
        self.client, self.futures, self.desc = client, futures, desc
        self.wait_s = WORKER_WAIT_S if wait_s is None else wait_s
        self.poll_s = poll_s
        self.fired = False
        self._closed = threading.Event()
        self._thread = threading.Thread(target=self._watch, name="pipeline-worker-watch", daemon=True)

    def __enter__(self) -> WorkerWatch:
        self._thread.start()
        return self

    def __exit__(self, *exc_info: object) -> None:
        self._closed.set()  # not joined: a call to a lost scheduler may block it until the client gives up

    @property
    def error(self) -> PipelineError:
        """The failure a run reports once the watch has fired."""
        return PipelineError(f"{self.desc}: the Dask cluster has had no workers for {self.wait_s:g} s (they died or "
                             "were stopped)")

    def _watch(self) -> None:
        workerless_since: float | None = None
        while not self._closed.wait(self.poll_s):
            try:
                threads = sum(self.client.nthreads().values())
            except Exception:  # the scheduler is gone or busy: the client's own calls fail or wait on it
                continue
            if threads:
                workerless_since = None
                continue
            if workerless_since is None:
                workerless_since = time.monotonic()
            if time.monotonic() - workerless_since >= self.wait_s and not self._closed.is_set():
                self.fired = True
                self.client.cancel(self.futures())
                return
