"""Running a run's tasks: on a Dask cluster (pipeline.engine.dask_cluster) or on threads of this process, results in
item order."""
from __future__ import annotations

import time
from concurrent.futures import FIRST_COMPLETED, Executor, wait
from concurrent.futures.process import BrokenProcessPool
from typing import TYPE_CHECKING, Any, Callable, ContextManager, Sequence

import numpy as np

from pipeline.engine.threads import in_process, local_workers
from pipeline.engine.worker_watch import WorkerWatch
from pipeline.errors import PipelineError, file_system_error
from pipeline.progress import Progress

if TYPE_CHECKING:
    from dask.distributed import Client


def cluster(workers: int, memory_limit: str, scheduler: str | None, here: bool = False,
            tile_processes: bool = False) -> ContextManager[Client | Executor]:
    """The scheduler's cluster when one is named, else `workers` threads of this process when `here`
    (capped at the cores, as local workers are; with `tile_processes`, the tiles' surveys and picks in as many
    worker processes), else a fresh local cluster."""
    if here and not scheduler:
        return in_process(local_workers(workers), tile_processes)
    from pipeline.engine.dask_cluster import connect, local_cluster

    return connect(scheduler) if scheduler else local_cluster(workers, memory_limit)


IN_FLIGHT_PER_THREAD = 2  # tasks unfinished per worker thread: one running, one queued so no round trip is waited
# for; Dask places a task when it is submitted, so a deeper queue left a worker idle while the other held
# several (lone-star: one of two workers idle for 3 s of a 6 s run)
RECOUNT_SECONDS = 5.0  # how often the window follows the cluster's thread count (workers may join later)


def map_tasks(client: Client | Executor, function: Callable, items: Sequence[Any], *shared: Any, desc: str,
              progress: Progress, weight: Callable[[Any], int] = lambda result: 0,
              cost: Callable[[Any], int] | None = None) -> list[Any]:
    """function(item, *shared) for every item on the cluster, or on the threads of an in-process run's
    executor; results in item order.

    `shared` values become one task each that every task depends on, copied to every worker before the
    tasks; unlike scattered data, the scheduler can recompute them if the workers holding them die. Tasks
    of a lost worker are rerun elsewhere (Dask allows 3 losses a task). Tasks are submitted in
    submission_order, IN_FLIGHT_PER_THREAD per worker thread ahead of the finished ones, not all at once: the
    client and scheduler then hold a bounded number of tasks whatever the tile count (all at once, the
    run's own process grew by about 37 KB a tile, 55 MiB for 1,517 tiles). The threads are recounted
    every RECOUNT_SECONDS, so workers that join an adaptive cluster mid-run get work. Progress counts
    finished tasks and, through `weight`, points per second. With `cost` (an item's expected work), the
    costly items are submitted first (submission_order): a scan with a few dominant tiles then starts
    them at once instead of running one alone at the phase's end; results stay in item order.
    """
    if isinstance(client, Executor):
        return _map_here(client, function, items, shared, desc, progress, weight, cost)
    unfinished: dict[Any, int] = {}  # the futures not yet returned: the tasks' item positions, -1 for shared values
    with WorkerWatch(client, lambda: list(unfinished.copy()), desc) as watch:
        try:
            return _map_on_cluster(client, function, items, shared, desc, progress, weight, cost, unfinished)
        except Exception:
            if watch.fired:
                raise watch.error from None
            raise


def _map_on_cluster(client: Client, function: Callable, items: Sequence[Any], shared: tuple, desc: str,
                    progress: Progress, weight: Callable[[Any], int], cost: Callable[[Any], int] | None,
                    unfinished: dict[Any, int]) -> list[Any]:
    """map_tasks on a Dask cluster, its unfinished futures in `unfinished` (a finished one is let go, so that
    the cluster may free its result)."""
    from dask.distributed import as_completed as completed_futures
    from distributed.scheduler import KilledWorker

    shared_futures = [client.submit(_same, value, pure=False) for value in shared]
    unfinished.update(dict.fromkeys(shared_futures, -1))
    if shared_futures:  # on every worker before any task runs: a busy worker is slow to send it
        client.replicate(shared_futures)
    results: list[Any] = [None] * len(items)
    running = completed_futures(loop=client.loop)
    window = Window(client)
    order = submission_order(items, cost)

    def top_up(submitted: int) -> int:
        """Submit the next items until the window is full; return how many are submitted in all."""
        while submitted < len(items) and len(unfinished) - len(shared_futures) < window.size():
            future = client.submit(function, items[order[submitted]], *shared_futures, pure=False)
            unfinished[future] = int(order[submitted])
            running.add(future)
            submitted += 1
        return submitted

    submitted = top_up(0)
    if shared_futures:  # again, now that tasks wait on them: between the two, Dask's memory manager may have
        client.replicate(shared_futures)  # dropped a copy no task needed yet (ReduceReplicas, every 2 s)
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
                                        "of memory: raise --memory-limit or lower --max-tile-points (or --tile-size, "
                                        "if the run noted a sub-cell over that limit)") from None
                raise task_failure(desc, exc) from exc
            results[unfinished.pop(future)] = result
            phase.update(1, weight(result))
            submitted = top_up(submitted)
    return results


def task_failure(desc: str, exc: Exception) -> PipelineError:
    """The one line for a task's failure: a file-system error (a scratch disk that filled) as the system says it,
    naming the file where it does; anything else with its type."""
    if isinstance(exc, OSError):
        return PipelineError(f"{desc}: {file_system_error(exc)}")
    return PipelineError(f"{desc} task failed: {type(exc).__name__}: {exc}")


def submission_order(items: Sequence[Any], cost: Callable[[Any], int] | None) -> np.ndarray:
    """(items,) positions in the order to submit them: the items costlier than the mean first, costliest
    first (the longest-first rule: the last to finish is then a short one), then the rest in item order
    (so neighbouring tiles, which share stored chunks, stay together). On lone-star's 9 tiles, the survey's
    2-thread makespan from measured tile times: 0.91 s with the costly ones in item order, 0.83 longest first."""
    if cost is None or not len(items):  # none left (a resumed run's finished phase): no mean to take
        return np.arange(len(items))
    costs = np.array([cost(item) for item in items], dtype=float)
    costly = costs > costs.mean()
    return np.lexsort((np.where(costly, -costs, 0.0), ~costly))


PROCESS_LOSSES = 3  # times a pool of tile processes may lose a worker in one phase (Dask allows a task 3 too)


def _map_here(pool: Executor, function: Callable, items: Sequence[Any], shared: tuple, desc: str,
              progress: Progress, weight: Callable[[Any], int], cost: Callable[[Any], int] | None) -> list[Any]:
    """map_tasks on this process's task threads (and tile processes: pipeline.engine.processes): the same
    calls, in the same submission order, failures reported as a worker's are; the first failure cancels the
    tasks not started. Tile processes get the `shared` values once each (processes.SentOnce), not with
    every task. A pool of tile processes that loses one (killed: out of memory?) fails every task it held:
    it is started afresh and those tasks given to it again, up to PROCESS_LOSSES times."""
    order = [int(position) for position in submission_order(items, cost)]
    shared = pool.shared(function, shared) if hasattr(pool, "shared") else shared  # tile processes: sent once
    futures = {pool.submit(function, items[position], *shared): position for position in order}
    results: list[Any] = [None] * len(items)
    losses = 0
    with progress.phase(desc, len(items)) as phase:
        try:
            while futures:
                done, _ = wait(futures, return_when=FIRST_COMPLETED)
                if any(not future.cancelled() and isinstance(future.exception(), BrokenProcessPool) for future in done):
                    done, _ = wait(futures)  # the broken pool fails all it held at once: take them together
                lost = []
                for future in done:
                    position = futures.pop(future)
                    try:
                        results[position] = future.result()
                    except (PipelineError, KeyboardInterrupt):
                        raise
                    except BrokenProcessPool:
                        lost.append(position)
                        continue
                    except Exception as exc:
                        raise task_failure(desc, exc) from exc
                    phase.update(1, weight(results[position]))
                if lost:
                    losses += 1
                    if not hasattr(pool, "restart"):
                        raise PipelineError(f"{desc}: a worker process died (killed, or out of memory?)")
                    if losses > PROCESS_LOSSES:
                        raise PipelineError(f"{desc}: worker processes died {losses} times (killed, out of memory, or "
                                            "started by a script that calls pipeline.run outside "
                                            "`if __name__ == \"__main__\":`?)")
                    pool.restart()
                    again = set(lost)
                    futures.update({pool.submit(function, items[position], *shared): position
                                    for position in order if position in again})
        except BaseException:
            for future in futures:
                future.cancel()
            raise
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
