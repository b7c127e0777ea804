"""A real dask.distributed cluster (a `dask scheduler` and two `dask worker` processes on 127.0.0.1),
and determinism: the same output for 1, 2 and 4 local workers and for the cluster."""
from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import threading
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import laspy
import numpy as np
import pytest
from dask.distributed import Client

import pipeline

REPO = Path(__file__).resolve().parents[1]
SETTINGS = dict(ratio=0.1, method="learned", tile_size=8.0, seed=3)


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@contextmanager
def dask_cluster(workers: int, *worker_options: str) -> Iterator[tuple[str, list[subprocess.Popen]]]:
    """tcp:// address of a scheduler with `workers` single-threaded workers, all separate processes, and the
    workers' processes."""
    address = f"tcp://127.0.0.1:{free_port()}"
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    scheduler_process = subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1",
                                          "--port", address.rsplit(":", 1)[1], "--no-dashboard"],
                                         env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    worker_processes = [subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker", address, "--nthreads",
                                          "1", "--no-dashboard", "--memory-limit", "2GB", *worker_options],
                                         env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
                        for _ in range(workers)]
    try:
        with Client(address, timeout="60s") as client:
            client.wait_for_workers(workers, timeout=120)
        yield address, worker_processes
    finally:
        for process in [scheduler_process, *worker_processes]:
            process.terminate()
        for process in [scheduler_process, *worker_processes]:
            process.wait(timeout=60)


@pytest.fixture(scope="module")
def scheduler() -> Iterator[str]:
    """tcp:// address of a scheduler with two single-threaded workers, all separate processes."""
    with dask_cluster(2) as (address, _):
        yield address


@pytest.fixture(scope="module")
def scan(street_scan: Path) -> Path:
    return street_scan


@pytest.fixture(scope="module")
def local_output(scan: Path, tmp_path_factory: pytest.TempPathFactory) -> np.ndarray:
    out = tmp_path_factory.mktemp("local") / "local.laz"
    pipeline.run(scan, out, workers=2, **SETTINGS)
    return laspy.read(out).points.array


@pytest.mark.parametrize("workers", [1, 4])
def test_worker_count_does_not_change_the_output(scan, local_output, tmp_path, workers):
    pipeline.run(scan, tmp_path / "out.laz", workers=workers, **SETTINGS)
    np.testing.assert_array_equal(laspy.read(tmp_path / "out.laz").points.array, local_output)


def test_a_real_cluster_gives_the_local_output(scan, local_output, scheduler, tmp_path):
    report = pipeline.run(scan, tmp_path / "out.laz", scheduler=scheduler, **SETTINGS)
    assert report.output_points == len(local_output)
    np.testing.assert_array_equal(laspy.read(tmp_path / "out.laz").points.array, local_output)


def test_cli_runs_on_the_cluster(scan, local_output, scheduler, tmp_path):
    out = tmp_path / "cli.laz"
    result = subprocess.run([sys.executable, "-m", "pipeline.apps.cli", "run", str(scan), "-o", str(out), "--ratio", "0.1",
                             "--method", "learned", "--tile-size", "8", "--seed", "3", "--scheduler", scheduler],
                            capture_output=True, text=True, cwd=REPO)
    assert result.returncode == 0, result.stderr
    np.testing.assert_array_equal(laspy.read(out).points.array, local_output)


def test_relative_paths_reach_workers_started_in_another_folder(scan, local_output, scheduler, tmp_path):
    """The workers run in their own folder (here the repository's), so an input, output and scratch folder named
    relative to the caller's failed there ('cannot read ... corrupt?', a missing store): they go as whole paths."""
    shutil.copy(scan, tmp_path / "in.laz")
    (tmp_path / "scratch").mkdir()
    result = subprocess.run([sys.executable, "-m", "pipeline.apps.cli", "run", "in.laz", "-o", "rel.laz", "--ratio",
                             "0.1", "--method", "learned", "--tile-size", "8", "--seed", "3", "--scratch", "scratch",
                             "--scheduler", scheduler], capture_output=True, text=True, cwd=tmp_path,
                            env={**os.environ, "PYTHONPATH": str(REPO)})
    assert result.returncode == 0, result.stderr
    np.testing.assert_array_equal(laspy.read(tmp_path / "rel.laz").points.array, local_output)


def test_an_unreachable_scheduler_is_one_line(scan, tmp_path):
    result = subprocess.run([sys.executable, "-m", "pipeline.apps.cli", "run", str(scan), "-o", str(tmp_path / "x.laz"),
                             "--ratio", "0.1", "--scheduler", f"tcp://127.0.0.1:{free_port()}"],
                            capture_output=True, text=True, cwd=REPO)
    assert result.returncode == 2
    assert result.stderr.startswith("pipeline: error: tcp://127.0.0.1:") and len(result.stderr.splitlines()) == 1
    assert not (tmp_path / "x.laz").exists()


def test_a_run_whose_workers_all_die_stops_and_says_why(scan, tmp_path, monkeypatch):
    """Dask waits for ever for workers to come back (a scheduled job would hang): a run stops once its cluster
    has had none for WORKER_WAIT_S and says so in one line, writing no output."""
    from pipeline.engine import worker_watch
    from pipeline.errors import PipelineError

    monkeypatch.setattr(worker_watch, "WORKER_WAIT_S", 2.0)
    out = tmp_path / "out.laz"
    with dask_cluster(1, "--no-nanny") as (address, [worker]):
        def kill_once_busy() -> None:
            with Client(address, timeout="60s", set_as_default=False) as watcher:  # closed after the run's client:
                # as the default it would restore the run's, leaving later tests' dask calls on a closed client
                while not any(watcher.processing().values()) and worker.poll() is None:
                    threading.Event().wait(0.05)
            worker.kill()

        killer = threading.Thread(target=kill_once_busy)
        killer.start()
        try:
            with pytest.raises(PipelineError, match=r": the Dask cluster has had no workers for 2 s \(") as error:
                pipeline.run(scan, out, scheduler=address, **SETTINGS)
        finally:
            killer.join()
    assert "\n" not in str(error.value)
    assert not out.exists()


def test_tasks_are_submitted_a_bounded_window_ahead_and_come_back_in_order(scheduler, monkeypatch):
    """map_tasks keeps at most IN_FLIGHT_PER_THREAD tasks per worker thread unfinished, not every tile's
    task at once (the run's own process grew by about 37 KB a tile), and returns results in item order."""
    import operator

    from pipeline.engine import execute
    from pipeline.progress import Progress

    monkeypatch.setattr(execute, "IN_FLIGHT_PER_THREAD", 2)
    with Client(scheduler, timeout="60s") as client:
        submitted = []
        most_unfinished = [0]
        submit = client.submit

        def counting_submit(*args, **kwargs):
            most_unfinished[0] = max(most_unfinished[0], sum(not f.done() for f in submitted[1:]))
            future = submit(*args, **kwargs)
            submitted.append(future)
            return future

        monkeypatch.setattr(client, "submit", counting_submit)
        items = list(range(200))
        results = execute.map_tasks(client, operator.sub, items, 7, desc="test", progress=Progress("off"))
    assert results == [item - 7 for item in items]  # in item order, the shared value passed to each
    assert 1 <= most_unfinished[0] <= 2 * 2  # two per thread, two single-threaded workers


def test_costly_tasks_go_first_and_every_worker_holds_the_shared_values(scheduler, monkeypatch):
    """Items costlier than the mean are submitted first (a dominant tile must not run alone at a phase's
    end), and the shared values are on every worker before any task starts (a worker busy with a task is
    slow to send them: the other one sat idle); results still come back in item order."""
    from pipeline.engine import execute
    from pipeline.progress import Progress

    def shared_value_holders(item: int, shared: str) -> tuple[int, int]:
        """The item, and how many workers hold this task's shared values as it starts (defined here: sent by
        value). Only its own dependencies count: a previous test's released values may linger a moment."""
        from distributed import get_client
        from distributed.worker import thread_state

        counts = get_client().run_on_scheduler(
            lambda key, dask_scheduler: [len(dependency.who_has or ())
                                         for dependency in dask_scheduler.tasks[key].dependencies],
            thread_state.key)
        return item, min(counts)

    with Client(scheduler, timeout="60s") as client:
        submitted = []
        submit = client.submit

        def recording_submit(function, *args, **kwargs):
            if function is shared_value_holders:
                submitted.append(args[0])
            return submit(function, *args, **kwargs)

        monkeypatch.setattr(client, "submit", recording_submit)
        costs = [1, 9, 2, 8, 1, 1]
        results = execute.map_tasks(client, shared_value_holders, list(range(6)), "plan", desc="test",
                                    progress=Progress("off"), cost=lambda item: costs[item])
    assert submitted == [1, 3, 0, 2, 4, 5]
    assert [item for item, _ in results] == list(range(6))
    # the first window (two tasks per worker): later, Dask's memory manager may drop a replica no waiting
    # task needs any more (ReduceReplicas), which is its job and not a fault of the run
    assert all(results[item][1] == 2 for item in submitted[:4])


def test_the_window_grows_when_a_worker_joins_mid_run(scheduler, monkeypatch):
    """An adaptive cluster adds workers while a run goes on: the window is recounted, so they get tasks."""
    from pipeline.engine import execute
    monkeypatch.setattr(execute, "RECOUNT_SECONDS", 0.0)
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    with Client(scheduler, timeout="60s") as client:
        window = execute.Window(client)
        assert window.size() == execute.IN_FLIGHT_PER_THREAD * 2
        joining = subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker", scheduler, "--nthreads", "1",
                                    "--no-dashboard", "--memory-limit", "1GB"],
                                   env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            client.wait_for_workers(3, timeout=120)
            assert window.size() == execute.IN_FLIGHT_PER_THREAD * 3
        finally:
            joining.terminate()
            joining.wait(timeout=60)
