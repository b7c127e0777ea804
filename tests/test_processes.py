"""Worker processes for an in-process run's tile work (pipeline.engine.processes): what goes there, what stays on
the run's threads, and a worker that dies."""
from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path
from concurrent.futures import ThreadPoolExecutor
from concurrent.futures.process import BrokenProcessPool, _RemoteTraceback

import pytest

from pipeline.engine.execute import PROCESS_LOSSES, map_tasks
from pipeline.engine.processes import TilesElsewhere, tile_processes, use_tile_processes
from pipeline.engine.tasks import simplify_tile, survey_tile
from pipeline.errors import PipelineError
from pipeline.progress import Progress


def test_only_a_big_scan_of_a_method_with_heavy_tiles_gives_them_to_processes():
    """fps (fpsample holds the GIL) from 1M points, voxel from 2M and the fill family (their surveys and hole
    covers hold it a fair share) from 300k: measured faster in processes from about there (voxel: a tie on a 2M
    street, 0.15 s lost on a 1M one, bcts_1..4's 2.8M simplified 1.78 -> 1.35 s); random lost; tcp and the
    paper's network were not measured (the network would import torch in each process)."""
    from model.registry import REGISTERED

    starts = {name: method.tile_processes_from for name, method in REGISTERED.items()
              if method.tile_processes_from is not None}
    assert starts == {"fps": 1_000_000, "voxel": 2_000_000, "stratified": 300_000, "stratified-detail": 300_000,
                      "learned": 300_000}
    assert use_tile_processes(300_000, 2, 300_000)
    assert not use_tile_processes(299_999, 2, 300_000)
    assert not use_tile_processes(300_000, 1, 300_000)  # one thread: nothing to run beside it
    assert not use_tile_processes(10**9, 2, None)


def test_surveys_and_picks_run_in_a_worker_process_and_everything_else_on_the_threads():
    with ThreadPoolExecutor(1) as threads, TilesElsewhere(threads, 1) as executor:
        assert executor.submit(os.getpid).result() == os.getpid()
        for tile_work in (survey_tile, simplify_tile):
            failed = executor.submit(tile_work, None, None).exception()  # a job of None fails where it runs
            assert isinstance(failed, AttributeError) and isinstance(failed.__cause__, _RemoteTraceback)


def test_a_worker_process_that_dies_is_one_line():
    with tile_processes(1) as pool:
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
    with ThreadPoolExecutor(1) as threads, TilesElsewhere(threads, 2, tile_work=(dies_the_first_time,)) as executor:
        results = map_tasks(executor, dies_the_first_time, list(range(6)), str(tmp_path / "died"), desc="simplify",
                            progress=Progress("off"))
    assert results == [0, 2, 4, 6, 8, 10]


RECEIVED: list[object] = []  # what a process's kept_and_counted calls received: alive, so no id is reused


def kept_and_counted(item: int, shared: dict[str, list[int]]) -> tuple[int, int, int]:
    """The item, the last of the shared value's cells, and how many distinct shared objects this process has
    received so far."""
    RECEIVED.append(shared)
    return item, shared["cells"][-1], len({id(value) for value in RECEIVED})


def test_a_value_every_tile_task_shares_reaches_each_worker_process_once():
    """The plan goes to a tile process once, not with each of its tasks (bcts_1..4's plan is 68 KB, for 91
    tasks a phase), and its file goes with the executor."""
    plan = {"cells": list(range(10_000))}
    with ThreadPoolExecutor(1) as threads, TilesElsewhere(threads, 2, tile_work=(kept_and_counted,)) as executor:
        results = map_tasks(executor, kept_and_counted, list(range(12)), plan, desc="simplify",
                            progress=Progress("off"))
        assert executor.folder is not None
        folder = Path(executor.folder.name)
        assert len(list(folder.iterdir())) == 1
    assert [(item, last) for item, last, _ in results] == [(item, 9_999) for item in range(12)]
    assert {distinct for _, _, distinct in results} == {1}
    assert not folder.exists()


def test_a_pool_that_keeps_losing_workers_ends_the_run_in_one_line():
    with ThreadPoolExecutor(1) as threads, TilesElsewhere(threads, 1, tile_work=(os._exit,)) as executor:
        with pytest.raises(PipelineError, match=rf"^simplify: worker processes died {PROCESS_LOSSES + 1} times \(killed"):
            map_tasks(executor, os._exit, [3, 4], desc="simplify", progress=Progress("off"))


def test_tile_processes_end_with_the_run_that_started_them(tmp_path):
    """A run killed outright (SIGKILL, an out-of-memory kill) takes its forkserver and workers with it: a
    worker would otherwise wait on its task queue for ever."""
    script = tmp_path / "killed.py"
    script.write_text(
        "import os, signal\n"
        "from pipeline.engine.processes import tile_processes\n"
        "if __name__ == '__main__':\n"
        "    pool = tile_processes(1)\n"
        "    print(pool.submit(os.getpid).result(), flush=True)\n"
        "    os.kill(os.getpid(), signal.SIGKILL)\n")
    printed = tmp_path / "worker.txt"
    with printed.open("w") as stdout:  # a file, not a pipe: a surviving worker would hold a pipe open
        subprocess.run([sys.executable, str(script)], stdout=stdout, timeout=60)
    worker = int(printed.read_text().split()[0])
    for _ in range(100):  # up to 10 s
        if not Path(f"/proc/{worker}").exists() or "State:\tZ" in Path(f"/proc/{worker}/status").read_text():
            break
        time.sleep(0.1)
    else:
        os.kill(worker, 9)
        pytest.fail(f"tile process {worker} outlived the killed run")


def test_a_run_started_while_a_worker_imports_its_script_is_refused(tmp_path, monkeypatch):
    """A script without a __main__ guard, re-imported by a worker, must not start a second run on its files."""
    import multiprocessing

    import pipeline

    monkeypatch.setattr(multiprocessing.current_process(), "_inheriting", True, raising=False)
    with pytest.raises(PipelineError, match="__name__ == \"__main__\""):
        pipeline.run(tmp_path / "scan.laz", tmp_path / "out.laz", ratio=0.1)


def test_a_pool_broken_before_a_phase_starts_afresh_for_it(tmp_path):
    """A worker killed between phases (while the run reads, say) breaks the pool before anything is given to
    it: the phase's first submits fail as its tasks would, and the pool starts afresh."""
    marker = tmp_path / "died"
    marker.touch()  # dies_the_first_time then just doubles
    with ThreadPoolExecutor(1) as threads, TilesElsewhere(threads, 1, tile_work=(dies_the_first_time,)) as executor:
        assert isinstance(executor.processes.submit(os._exit, 9).exception(), BrokenProcessPool)
        results = map_tasks(executor, dies_the_first_time, [1, 2], str(marker), desc="simplify", progress=Progress("off"))
    assert results == [2, 4]


def sigterm_disposition(answers) -> None:
    """Report this process's SIGTERM disposition (run in a process forked from the forkserver)."""
    import signal

    answers.put(signal.getsignal(signal.SIGTERM) == signal.SIG_DFL)


def test_the_forkserver_outlives_sigterm_but_what_it_forks_does_not():
    """The server ignores SIGTERM, so a stop sent to the run's process group cannot break the pool under the
    run; any other process forked from it (not a tile worker, which ignores SIGTERM in its setup) has SIGTERM's
    default again."""
    import multiprocessing
    import signal
    from multiprocessing import forkserver

    with tile_processes(1) as pool:
        assert pool.submit(signal.getsignal, signal.SIGTERM).result() == signal.SIG_IGN  # a worker ignores it
        server = forkserver._forkserver._forkserver_pid
        ignored = int(next(line for line in Path(f"/proc/{server}/status").read_text().splitlines()
                           if line.startswith("SigIgn:")).split()[1], 16)
        assert ignored & (1 << (signal.SIGTERM - 1))
        context = multiprocessing.get_context("forkserver")
        answers = context.Queue()
        other = context.Process(target=sigterm_disposition, args=(answers,))
        other.start()
        assert answers.get(timeout=60) is True
        other.join(timeout=60)


def test_compare_from_a_script_without_a_main_guard_ends_in_a_line_that_says_so(tmp_path, street_scan):
    """compare's runs share a local cluster whose spawned workers import the calling script again: without a
    __main__ guard each worker started a compare of its own and Dask ended in 'Nanny failed to start'."""
    script = tmp_path / "unguarded.py"
    script.write_text("import pipeline\n"
                      f"pipeline.compare({str(street_scan)!r}, ratios=[0.1], methods=['random'], "
                      f"out_dir={str(tmp_path / 'out')!r}, workers=1, sample=0)\n")
    result = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300,
                            env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])})
    assert result.returncode != 0
    assert result.stderr.strip().splitlines()[-1].endswith(
        'must do so under `if __name__ == "__main__":`, as each worker imports it again')
