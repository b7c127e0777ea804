"""Running a run's tasks: on a Dask cluster (pipeline.dask_cluster) or in this process, results in item order."""
from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any, Callable, ContextManager, Sequence

from pipeline.errors import PipelineError
from pipeline.progress import Progress
from pipeline.threads import in_process

if TYPE_CHECKING:
    from dask.distributed import Client


def cluster(workers: int, memory_limit: str, scheduler: str | None,
            here: bool = False) -> ContextManager[Client | None]:
    """The scheduler's cluster when one is named, else this process when `here` (no client: map_tasks runs
    the tasks in line), else a fresh local cluster."""
    if here and not scheduler:
        return in_process()
    from pipeline.dask_cluster import connect, local_cluster

    return connect(scheduler) if scheduler else local_cluster(workers, memory_limit)


IN_FLIGHT_PER_THREAD = 4  # tasks submitted ahead per worker thread: enough to keep every worker busy
RECOUNT_SECONDS = 5.0  # how often the window follows the cluster's thread count (workers may join later)


def map_tasks(client: Client | None, function: Callable, items: Sequence[Any], *shared: Any, desc: str,
              progress: Progress, weight: Callable[[Any], int] = lambda result: 0) -> list[Any]:
    """function(item, *shared) for every item on the cluster (in item order, in this process, without a
    client); results in item order.

    `shared` values become one task each that every task depends on, so a worker fetches them once;
    unlike scattered data, the scheduler can recompute them if the workers holding them die. Tasks
    of a lost worker are rerun elsewhere (Dask allows 3 losses a task). Tasks are submitted in item
    order, IN_FLIGHT_PER_THREAD per worker thread ahead of the finished ones, not all at once: the
    client and scheduler then hold a bounded number of tasks whatever the tile count (all at once, the
    run's own process grew by about 37 KB a tile, 55 MiB for 1,517 tiles). The threads are recounted
    every RECOUNT_SECONDS, so workers that join an adaptive cluster mid-run get work. Progress counts
    finished tasks and, through `weight`, points per second.
    """
    if client is None:
        return _map_here(function, items, shared, desc, progress, weight)
    from dask.distributed import as_completed
    from distributed.scheduler import KilledWorker

    shared_futures = [client.submit(_same, value, pure=False) for value in shared]
    position: dict[str, int] = {}  # the unfinished tasks' item positions, by key
    results: list[Any] = [None] * len(items)
    running = as_completed(loop=client.loop)
    window = Window(client)

    def top_up(submitted: int) -> int:
        """Submit the next items until the window is full; return how many are submitted in all."""
        while submitted < len(items) and len(position) < window.size():
            future = client.submit(function, items[submitted], *shared_futures, pure=False)
            position[future.key] = submitted
            running.add(future)
            submitted += 1
        return submitted

    submitted = top_up(0)
    with progress.phase(desc, len(items)) as phase:
        for future in running:
            try:
                result = future.result()
            except Exception as exc:
                for pending in list(running.futures):
                    pending.cancel()
                if isinstance(exc, PipelineError):
                    raise
                if isinstance(exc, KilledWorker):
                    raise PipelineError(f"{desc}: the workers running one task died again and again, most likely out "
                                        "of memory: raise --memory-limit or lower --max-tile-points") from None
                raise PipelineError(f"{desc} task failed: {type(exc).__name__}: {exc}") from exc
            results[position.pop(future.key)] = result
            phase.update(1, weight(result))
            submitted = top_up(submitted)
    return results


def _map_here(function: Callable, items: Sequence[Any], shared: tuple, desc: str, progress: Progress,
              weight: Callable[[Any], int]) -> list[Any]:
    """map_tasks in this process: the same calls, one after another, failures reported as a worker's are."""
    results = []
    with progress.phase(desc, len(items)) as phase:
        for item in items:
            try:
                results.append(function(item, *shared))
            except (PipelineError, KeyboardInterrupt):
                raise
            except Exception as exc:
                raise PipelineError(f"{desc} task failed: {type(exc).__name__}: {exc}") from exc
            phase.update(1, weight(results[-1]))
    return results


class Window:
    """How many tasks may be unfinished at once: IN_FLIGHT_PER_THREAD per worker thread of the cluster,
    recounted every RECOUNT_SECONDS (asking the scheduler costs a round trip)."""

    def __init__(self, client: Client) -> None:
        self.client = client
        self._recount()

    def size(self) -> int:
        """The current window, in tasks (at least IN_FLIGHT_PER_THREAD, for a cluster between workers)."""
        if time.monotonic() - self.counted_at >= RECOUNT_SECONDS:
            self._recount()
        return self.tasks

    def _recount(self) -> None:
        self.tasks = IN_FLIGHT_PER_THREAD * max(sum(self.client.nthreads().values()), 1)
        self.counted_at = time.monotonic()


def _same(value: Any) -> Any:
    """The value itself: a task that holds `value`, so losing its result loses nothing."""
    return value
