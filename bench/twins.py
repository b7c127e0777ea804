"""What a scanner's no-return spot costs a run: one position repeated hundreds of thousands of times (a static
scanner's zero-range returns at its origin, an export that writes invalid points at one place), against the
same count of points spread over the scene.

    python bench/twins.py [--points 2000000] [--twins 400000] [--ratio 0.1] [--methods learned,fps,voxel,random]
                          [--jitter 0.003]

Why: pykdtree's search for 4 or more neighbours of a twin, and fpsample's picks once every point left is a
twin, pass over all of a position's twins each time: quadratic in the spot. A 2M-point scan with 400,000 twins
took 246 s with the default method at 0.3.12 (4 s after model.geometry.PointTree and
model.baselines.distinct_fps_order). Prints wall seconds with and without the spot, and how many output points
the spot kept (one is all a position needs). With --jitter the spot's returns scatter by that standard deviation
(metres, on a 0.1 mm grid: distinct points, a blob on the tiles' corner), which the seam pass once paired all
with each other (100,000 of them on 400,000: 261 s in the stitch).
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import laspy
import numpy as np

SPOT = (150.0, 150.0, 0.0)  # metres: the middle of the 300 m scene


def write_scene(path: Path, points: int, twins: int, jitter: float = 0.0, seed: int = 2) -> None:
    """A 300 m gently waved sheet of `points` points, the first `twins` of them moved onto SPOT (scattered by
    `jitter` m, on a grid 10x finer)."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 300, (points, 2))
    xyz = np.column_stack([xy, 0.1 * np.sin(xy[:, 0]) + rng.normal(0, 0.01, points)])
    xyz[:twins] = SPOT + rng.normal(0, jitter, (twins, 3)) if jitter > 0 else SPOT
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales, header.offsets = [0.0001 if jitter > 0 else 0.001] * 3, [0.0] * 3
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz.T
    las.intensity = rng.integers(0, 4000, points)
    las.write(path)


def timed_run(source: Path, method: str, ratio: float, out: Path, within: float) -> tuple[float, int]:
    """Wall seconds of `pipeline run` (2 workers) and how many output points lie `within` m of SPOT."""
    start = time.perf_counter()
    subprocess.run([sys.executable, "-m", "pipeline.apps.cli", "run", str(source), "--ratio", str(ratio), "-m", method,
                    "-o", str(out), "--overwrite", "-q", "--workers", "2"], check=True)
    wall = time.perf_counter() - start
    kept = laspy.read(out)
    offset = np.column_stack([np.asarray(kept.x), np.asarray(kept.y), np.asarray(kept.z)]) - SPOT
    return wall, int((np.sqrt((offset * offset).sum(axis=1)) <= within).sum())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--points", type=int, default=2_000_000)
    parser.add_argument("--twins", type=int, default=400_000)
    parser.add_argument("--ratio", type=float, default=0.1)
    parser.add_argument("--methods", default="learned,fps,voxel,random")
    parser.add_argument("--jitter", type=float, default=0.0)
    args = parser.parse_args()
    within = 5 * args.jitter  # the spot's returns, scattered or not
    with tempfile.TemporaryDirectory() as work:
        spot, spread = Path(work) / "spot.las", Path(work) / "spread.las"
        write_scene(spot, args.points, args.twins, args.jitter)
        write_scene(spread, args.points, 0)
        print(f"{args.points:,} points, {args.twins:,} of them at one spot (scattered by {args.jitter} m), "
              f"ratio {args.ratio}, 2 workers\n")
        print("| method | wall s, with the spot | wall s, spread | with / spread | output points at the spot |")
        print("| --- | ---: | ---: | ---: | ---: |")
        for method in args.methods.split(","):
            with_spot, at_spot = timed_run(spot, method, args.ratio, Path(work) / "out.laz", within)
            without, _ = timed_run(spread, method, args.ratio, Path(work) / "out.laz", within)
            print(f"| {method} | {with_spot:.2f} | {without:.2f} | {with_spot / without:.2f} | {at_spot:,} |",
                  flush=True)


if __name__ == "__main__":
    main()
