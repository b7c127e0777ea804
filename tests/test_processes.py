"""Worker processes for an in-process run's picking (pipeline.engine.processes): what goes there, what stays on
the run's threads, and a worker that dies."""
from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from concurrent.futures.process import _RemoteTraceback

import pytest

from pipeline.engine.execute import map_tasks
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
    with ThreadPoolExecutor(1) as threads, PickingElsewhere(threads, picking_processes(1)) as executor:
        assert executor.submit(os.getpid).result() == os.getpid()
        failed = executor.submit(simplify_tile, None, None).exception()  # a job of None fails where it runs
    assert isinstance(failed, AttributeError) and isinstance(failed.__cause__, _RemoteTraceback)


def test_a_worker_process_that_dies_is_one_line():
    with picking_processes(1) as pool:
        with pytest.raises(PipelineError, match=r"^simplify: a worker process died \(killed, or out of memory\?\)$"):
            map_tasks(pool, os._exit, [3], desc="simplify", progress=Progress("off"))
