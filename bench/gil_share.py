"""How much of a simplifier's time holds Python's GIL: the same tile simplified on threads and in processes.

    python bench/gil_share.py [--method learned] [--points 100000] [--calls 2] [--workers N]

A simulated street tile (generated here, no shared data needed) is simplified at ratio 0.1 `calls` times
by each of `workers` threads of one process, then by each of `workers` processes, after `workers * calls`
calls on one thread. Each worker holds one BLAS/OpenMP thread, as pipeline workers do. Amdahl's law on the
two speed-ups gives the share f of a call that holds the GIL (processes set the machine's own efficiency),
and what f means for more cores: the reason scans up to `in_process_points` run on threads
(pipeline/engine/threads.py) and larger ones on a cluster.
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from functools import lru_cache
from pathlib import Path

os.environ.update({name: "1" for name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")})

import laspy  # noqa: E402  (after the thread settings, which BLAS reads as it loads)
import numpy as np  # noqa: E402

from model.registry import get_simplifier  # noqa: E402
from model.selection import Tile  # noqa: E402
from pipeline.simulate import write_street_scan  # noqa: E402
from pipeline.engine.threads import available_cores  # noqa: E402

RATIO = 0.1


@lru_cache(maxsize=1)
def street_tile(points: int) -> Tile:
    """One tile of `points` simulated street points, centred (built once per process)."""
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "street.laz"
        write_street_scan(path, points, seed=3)
        las = laspy.read(path)
    xyz = np.column_stack([las.x, las.y, las.z])
    return Tile(xyz - xyz.mean(axis=0), np.ones(len(xyz), bool), np.zeros(3), seed=1)


def simplify_calls(method: str, points: int, calls: int) -> float:
    """Seconds for `calls` simplifications of the tile (the tile itself built beforehand, untimed)."""
    tile, simplify = street_tile(points), get_simplifier(method)
    started = time.perf_counter()
    for _ in range(calls):
        simplify(tile, round(RATIO * points))
    return time.perf_counter() - started


def timed_pool(pool_type: type, method: str, points: int, calls: int, workers: int) -> float:
    """Wall seconds for `workers` pool members each making `calls` calls (after one untimed warm-up each)."""
    with pool_type(workers) as pool:
        list(pool.map(simplify_calls, [method] * workers, [points] * workers, [0] * workers))
        started = time.perf_counter()
        list(pool.map(simplify_calls, [method] * workers, [points] * workers, [calls] * workers))
        return time.perf_counter() - started


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--method", default="learned")
    parser.add_argument("--points", type=int, default=100_000)
    parser.add_argument("--calls", type=int, default=2)
    parser.add_argument("--workers", type=int, default=available_cores())
    args = parser.parse_args()
    workers, work = args.workers, (args.method, args.points)
    simplify_calls(*work, 1)  # imports and the tile, untimed
    alone = simplify_calls(*work, workers * args.calls)
    threads = timed_pool(ThreadPoolExecutor, *work, args.calls, workers)
    processes = timed_pool(ProcessPoolExecutor, *work, args.calls, workers)
    on_threads, in_processes = alone / threads, alone / processes
    efficiency = in_processes / workers
    held = (efficiency / on_threads - 1 / workers) / (1 - 1 / workers) if workers > 1 else float("nan")
    print(f"| method | points | workers | one thread s | {workers} threads s | {workers} processes s | "
          f"threads speed-up | processes speed-up | GIL share | 8 threads (Amdahl) |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    print(f"| {args.method} | {args.points:,} | {workers} | {alone:.2f} | {threads:.2f} | {processes:.2f} | "
          f"{on_threads:.2f} | {in_processes:.2f} | {held:.2f} | {1 / ((1 - held) / 8 + held):.1f} |")


if __name__ == "__main__":
    main()
