"""An in-process run's task threads: they run at once, fail as workers do, and what they share in the
process (fd 2 while lazrs decodes, the chunk cache) stays whole."""
from __future__ import annotations

import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import laspy
import numpy as np
import pytest

from pipeline.engine.execute import map_tasks
from pipeline.engine.threads import available_cores, in_process, runs_in_process
from pipeline.errors import PipelineError
from pipeline.io.las_source import LasSource
from pipeline.progress import Progress
from tiling.store import ChunkCache

OFF = Progress("off")


def test_tasks_run_on_as_many_threads_as_asked():
    meeting = threading.Barrier(2, timeout=60)  # one thread alone would wait here until the timeout breaks it

    def meet(item: int) -> int:
        meeting.wait()
        return threading.get_ident()

    with in_process(2) as pool:
        threads = map_tasks(pool, meet, [0, 1], desc="test", progress=OFF)
    assert len(set(threads)) == 2 and threading.get_ident() not in threads


def test_results_come_back_in_item_order_with_the_costly_items_run_first():
    ran: list[int] = []

    def record(item: int, offset: int) -> int:
        ran.append(item)
        return item + offset

    costs = [1, 8, 2, 9, 1, 1]
    with in_process(1) as pool:
        results = map_tasks(pool, record, list(range(6)), 100, desc="test", progress=OFF, cost=lambda item: costs[item])
    assert results == [100, 101, 102, 103, 104, 105]
    assert ran == [3, 1, 0, 2, 4, 5]  # above the mean cost first, costliest first, then the rest in item order


def test_a_failing_task_is_one_line_and_the_tasks_not_started_are_cancelled():
    ran: list[int] = []

    def fail_first(item: int) -> int:
        ran.append(item)
        if item == 0:
            raise ValueError("bad tile")
        time.sleep(0.05)  # a tile takes a while: with none, the one thread can run them all before the failure is read
        return item

    with in_process(1) as pool:
        with pytest.raises(PipelineError, match="^test task failed: ValueError: bad tile$"):
            map_tasks(pool, fail_first, list(range(50)), desc="test", progress=OFF)
    assert ran[0] == 0 and len(ran) <= 2  # the one thread may have taken the next item before the cancel


def test_concurrent_decodes_leave_fd_2_where_it_was(tmp_path):
    """Each decode sends fd 2 to a temporary file (to drop a lazrs panic's report): interleaved on two
    threads, one thread's restore would leave fd 2 on the other's temporary file."""
    header = laspy.LasHeader(version="1.2", point_format=1)
    header.scales, header.offsets = [0.01] * 3, [0.0] * 3
    las = laspy.LasData(header)
    las.x, las.y, las.z = np.random.default_rng(0).uniform(0, 50, (3, 20_000))
    las.write(tmp_path / "in.laz")
    source = LasSource(tmp_path / "in.laz")
    before = os.fstat(2)
    with ThreadPoolExecutor(4) as pool:
        counts = list(pool.map(lambda _: len(source.read(0, 20_000)), range(40)))
    after = os.fstat(2)
    assert counts == [20_000] * 40
    assert (after.st_dev, after.st_ino) == (before.st_dev, before.st_ino)


def test_the_chunk_cache_shared_by_threads_keeps_its_budget_and_its_rows():
    cache, budget = ChunkCache(), 40 * 8_000

    def chunk(key: int) -> np.ndarray:
        time.sleep(0.001)  # a read from disk: other threads ask for the same chunk meanwhile
        return np.full(1_000, key, dtype=np.int64)  # 8,000 bytes

    def fetch(key: int) -> bool:
        return bool((cache.get(("store", "p0", key), budget, lambda: chunk(key)) == key).all())

    with ThreadPoolExecutor(4) as pool:
        correct = list(pool.map(fetch, [k // 4 % 60 for k in range(3_000)]))  # four threads want each chunk
    assert all(correct)
    assert cache._bytes <= budget and cache._bytes == sum(a.nbytes for a in cache._arrays.values())


def test_more_threads_take_fewer_points_in_process():
    """`in_process_points` holds at 2 threads; with more, threads lose more to processes (the GIL), so the
    cluster's start pays off sooner: 667k points at 4 threads, 571k at 8; 0 always starts a cluster. A
    method light on the GIL runs three times as many points on threads, one whose tiles go to worker
    processes seven times as many (whether or not it is light on the GIL)."""
    limit = 1_000_000
    assert runs_in_process(limit, limit, 1) and runs_in_process(limit, limit, 2)
    assert not runs_in_process(limit + 1, limit, 2)
    assert runs_in_process(666_000, limit, 4) and not runs_in_process(667_000, limit, 4)
    assert runs_in_process(571_000, limit, 8) and not runs_in_process(572_000, limit, 8)
    assert not runs_in_process(1, 0, 2) and not runs_in_process(1, 0, 2, light_on_gil=True)
    assert runs_in_process(3 * limit, limit, 2, light_on_gil=True)
    assert not runs_in_process(3 * limit + 1, limit, 2, light_on_gil=True)
    for light in (False, True):
        assert runs_in_process(7 * limit, limit, 2, light, tile_processes=True)
        assert not runs_in_process(7 * limit + 1, limit, 2, light, tile_processes=True)
    assert not runs_in_process(1, 0, 2, tile_processes=True)


def test_the_methods_light_on_the_gil_are_the_compiled_ones():
    """fps (fpsample), voxel and random run in numpy and compiled code; the fill's hole cover and the
    paper's network hold the GIL far longer, so they keep the default limit."""
    from model.registry import REGISTERED

    assert {name for name, method in REGISTERED.items() if method.light_on_gil} == {"fps", "voxel", "random"}


@pytest.mark.skipif(available_cores() < 2, reason="one core: OpenMP's default is one thread already")
def test_task_threads_hold_openmp_to_one_thread_as_workers_do():
    """pykdtree's kNN runs on OpenMP, whose thread count is per thread: the run's own limit must reach the
    task threads, or `--workers 1` uses every core."""
    import pykdtree.kdtree  # noqa: F401  (loads the OpenMP runtime the kNN uses)
    from threadpoolctl import threadpool_info

    with in_process(2) as pool:
        seen = map_tasks(pool, lambda item: threadpool_info(), [0, 1], desc="test", progress=OFF)
    openmp = [info for infos in seen for info in infos if info["user_api"] == "openmp"]
    assert openmp and all(info["num_threads"] == 1 for info in openmp)


def test_the_in_process_run_gives_back_its_thread_settings():
    saved = {name: os.environ.get(name) for name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")}
    with in_process(2):
        assert os.environ["OMP_NUM_THREADS"] == "1"
    assert {name: os.environ.get(name) for name in saved} == saved


@pytest.fixture(autouse=True)
def no_stray_task_threads():
    """Leaving in_process waits for its threads: none may outlive the test."""
    yield
    assert not [t for t in threading.enumerate() if t.name.startswith("pipeline-task")]
