"""Worker processes for an in-process run's picking (pipeline.engine.processes): what goes there, what stays on
the run's threads, and a worker that dies."""
from __future__ import annotations

import os
from pathlib import Path
from concurrent.futures import ThreadPoolExecutor
from concurrent.futures.process import _RemoteTraceback

import pytest

from pipeline.engine.execute import PROCESS_LOSSES, map_tasks
from pipeline.engine.processes import PROCESS_PICKING_POINTS, PickingElsewhere, picking_processes, picks_in_processes
from pipeline.engine.tasks import simplify_tile
from pipeline.errors import PipelineError
from pipeline.progress import Progress


def test_only_a_big_scan_of_a_method_picking_under_the_gil_picks_in_processes():
    from model.registry import REGISTERED

    assert {name for name, method in REGISTERED.items() if method.picks_hold_gil} == {"fps"}
    assert picks_in_processes(PROCESS_PICKING_POINTS, 2, True)
    assert not picks_in_processes(PROCESS_PICKING_POINTS - 1, 2, True)
    assert not picks_in_processes(PROCESS_PICKING_POINTS, 1, True)  # one thread: nothing to run beside it
    assert not picks_in_processes(PROCESS_PICKING_POINTS, 2, False)


def test_picking_runs_in_a_worker_process_and_everything_else_on_the_threads():
    with ThreadPoolExecutor(1) as threads, PickingElsewhere(threads, 1) as executor:
        assert executor.submit(os.getpid).result() == os.getpid()
        failed = executor.submit(simplify_tile, None, None).exception()  # a job of None fails where it runs
    assert isinstance(failed, AttributeError) and isinstance(failed.__cause__, _RemoteTraceback)


def test_a_worker_process_that_dies_is_one_line():
    with picking_processes(1) as pool:
        with pytest.raises(PipelineError, match=r"^simplify: a worker process died \(killed, or out of memory\?\)$"):
            map_tasks(pool, os._exit, [3], desc="simplify", progress=Progress("off"))


def dies_the_first_time(item: int, marker: str) -> int:
    """Kill the process running it the first time any item runs (a marker file remembers), as an out-of-memory
    kill would; afterwards, the item doubled."""
    try:
        Path(marker).touch(exist_ok=False)
    except FileExistsError:
        return 2 * item
    os._exit(9)


def test_a_pool_that_loses_a_worker_starts_afresh_and_runs_its_tasks_again(tmp_path):
    with ThreadPoolExecutor(1) as threads, PickingElsewhere(threads, 2, picking=dies_the_first_time) as executor:
        results = map_tasks(executor, dies_the_first_time, list(range(6)), str(tmp_path / "died"), desc="simplify",
                            progress=Progress("off"))
    assert results == [0, 2, 4, 6, 8, 10]


def test_a_pool_that_keeps_losing_workers_ends_the_run_in_one_line():
    with ThreadPoolExecutor(1) as threads, PickingElsewhere(threads, 1, picking=os._exit) as executor:
        with pytest.raises(PipelineError, match=rf"^simplify: worker processes died {PROCESS_LOSSES + 1} times "):
            map_tasks(executor, os._exit, [3, 4], desc="simplify", progress=Progress("off"))
