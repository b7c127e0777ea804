"""Where a scan's tile time goes, per core point: why one kind of scan costs more per point than another.

    python bench/tile_costs.py [--inputs bcts,lone-star,autzen,street] [--method learned] [--ratio 0.1]
                               [--data ../shared/data/lidar] [--threads 2]

Runs each input in this process on one task thread (every tile's survey and simplify timed by the thread's
own CPU clock, tile loads apart), then prints per input: tiles, core points, the points a tile loads per
core point (its halo's weight), the survey's and the simplify step's microseconds per core point and the
share of both spent loading tiles, and what `--threads` task threads would take for each phase: the
makespan of the run's submission order (pipeline.engine.execute.submission_order, costs = core points)
over the measured tile times, against the ideal (total / threads, or the largest tile). A scan whose
per-core-point cost matches another's but whose wall time per point does not loses it to fixed costs or
to that makespan. `street` is a simulated 1M-point mobile scan, made here.
"""
from __future__ import annotations

import argparse
import heapq
import tempfile
import time
from collections import defaultdict
from pathlib import Path
from typing import Any, Callable

import pipeline
import pipeline.engine.phases as phases
import pipeline.engine.runner as runner
import pipeline.engine.tasks as tasks
from pipeline.engine.execute import submission_order
from pipeline.simulate import write_street_scan

INPUTS = {"bcts": ["bcts_1.laz", "bcts_2.laz", "bcts_3.laz", "bcts_4.laz"], "lone-star": ["lone-star.laz"],
          "autzen": ["autzen_trim.laz"]}


class TileClock:
    """Thread CPU seconds per (step, tile), and each tile's core and loaded point counts, from wrapped tasks."""

    def __init__(self) -> None:
        self.seconds: dict[tuple[str, int], float] = defaultdict(float)
        self.points: dict[int, tuple[int, int]] = {}

    def timed_step(self, function: Callable, step: str) -> Callable:
        """`function(job, ...)` timed on its thread's clock under `step` for job.tile_id."""
        def timed(job: Any, *args: Any, **kwargs: Any) -> Any:
            started = time.thread_time()
            try:
                return function(job, *args, **kwargs)
            finally:
                self.seconds[step, job.tile_id] += time.thread_time() - started
        return timed

    def timed_load(self, function: Callable) -> Callable:
        """tasks.load_tile timed as 'load', with the tile's core and loaded point counts noted."""
        def timed(*args: Any, **kwargs: Any) -> Any:
            started = time.thread_time()
            tile, records, whole = function(*args, **kwargs)
            tile_id = args[4]
            self.seconds["load", tile_id] += time.thread_time() - started
            self.points[tile_id] = (tile.core_count, len(tile.xyz))
            return tile, records, whole
        return timed


def makespan(order: list[int], seconds: dict[int, float], threads: int) -> float:
    """Wall seconds of tiles taken in `order` by `threads` threads, each taking the next when it is free."""
    free = [0.0] * threads
    for tile_id in order:
        heapq.heappush(free, heapq.heappop(free) + seconds.get(tile_id, 0.0))
    return max(free)


def measure(name: str, paths: list[Path], method: str, ratio: float, threads: int) -> str:
    """One Markdown row for the input."""
    clock = TileClock()
    originals = (phases.survey_tile, runner.simplify_tile, tasks.load_tile)
    phases.survey_tile = clock.timed_step(originals[0], "survey")
    runner.simplify_tile = clock.timed_step(originals[1], "simplify")
    tasks.load_tile = clock.timed_load(originals[2])
    try:
        with tempfile.TemporaryDirectory() as folder:
            pipeline.run(paths, Path(folder) / "out.laz", ratio=ratio, method=method, workers=1,
                         in_process_points=10**12)
    finally:
        phases.survey_tile, runner.simplify_tile, tasks.load_tile = originals
    tiles = sorted(clock.points)
    core = sum(clock.points[t][0] for t in tiles)
    loaded = sum(clock.points[t][1] for t in tiles)
    cells = [f"{name}", f"{len(tiles)}", f"{core:,}", f"{loaded / core:.2f}"]
    step_total = 0.0
    for step in ("survey", "simplify"):
        total = sum(clock.seconds[step, t] for t in tiles)
        step_total += total
        cells.append(f"{1e6 * total / core:.2f}" if total else "-")
    cells.append(f"{100 * sum(clock.seconds['load', t] for t in tiles) / step_total:.0f} %")
    order = [tiles[i] for i in submission_order(tiles, lambda t: clock.points[t][0])]
    for step in ("survey", "simplify"):
        per_tile = {t: clock.seconds[step, t] for t in tiles}
        if not any(per_tile.values()):
            cells.append("-")
            continue
        ideal = max(sum(per_tile.values()) / threads, max(per_tile.values()))
        cells.append(f"{makespan(order, per_tile, threads):.2f} / {ideal:.2f}")
    return "| " + " | ".join(cells) + " |"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--inputs", default="bcts,lone-star,autzen,street")
    parser.add_argument("--method", default="learned")
    parser.add_argument("--ratio", type=float, default=0.1)
    parser.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared/data/lidar")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        for name in args.inputs.split(","):
            if name == "street":
                paths = [Path(folder) / "street.laz"]
                write_street_scan(paths[0], 1_000_000, seed=0)
            else:
                paths = [args.data / file for file in INPUTS[name]]
                if not all(path.exists() for path in paths):
                    print(f"skipped {name}: {args.data} lacks {', '.join(INPUTS[name])}")
                    continue
            rows.append(measure(name, paths, args.method, args.ratio, args.threads))
            print(rows[-1], flush=True)
    print(f"\n`{args.method}` at {args.ratio}, one task thread, thread CPU clocks; us/pt = microseconds per core "
          f"point; load = tile loads' share of survey + simplify; makespan = {args.threads} threads in the run's "
          "submission order over the measured tile times / the ideal")
    print("| input | tiles | core points | loaded / core | survey us/pt | simplify us/pt | load | survey makespan s "
          "| simplify makespan s |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    print("\n".join(rows))


if __name__ == "__main__":
    main()
