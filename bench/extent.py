"""Memory and speed at any extent: the same points laid out compactly and spread over 100+ km.

    python bench/extent.py [--copies 10] [--points 300k] [--spacing-km 10] [--methods fps,learned]
                           [--data DIR]

Simulates one street scan, then writes `--copies` copies of it shifted along x (header offsets only, so
the points are identical): "compact" puts them side by side, "spread" puts them `--spacing-km` apart (10
copies 10 km apart: a 90 km corridor of sites; 2 copies 200 km apart: the two-sites case). Each layout
runs through `pipeline run` (2 workers) measured over its process tree; the largest tile comes from the
plan of the same points. Targets: the spread run's peak RSS within 1.2x and its throughput within 1.2x
of the compact run's, and no tile above `--max-tile-points` (200k) in either.
"""
from __future__ import annotations

import argparse
import re
import sys
import tempfile
from pathlib import Path

import laspy
import numpy as np
from proctree import Measured, measure

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from pipeline.simulate import write_street_scan  # noqa: E402
from scale import parse_count  # noqa: E402
from tiling.plan import DensityGrid, plan_tiles  # noqa: E402

SUMMARY = re.compile(r"of ([\d,]+) points \((\d+) tiles, ([\d.]+) s")
MAX_TILE_POINTS = 200_000


def shifted_copy(source: Path, target: Path, dx: float) -> None:
    """The scan moved dx along x by its header offset alone (records unchanged), streamed."""
    with laspy.open(source) as reader:
        header = reader.header
        header.offsets = header.offsets + [dx, 0.0, 0.0]
        header.mins, header.maxs = header.mins + [dx, 0, 0], header.maxs + [dx, 0, 0]
        with laspy.open(target, mode="w", header=header) as writer:
            for chunk in reader.chunk_iterator(500_000):
                writer.write_points(chunk)


def layout(base: Path, copies: int, step: float, folder: Path) -> list[Path]:
    """`copies` shifted copies of the base scan, `step` apart along x."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for number in range(copies):
        path = folder / f"part-{number}.laz"
        if not path.exists():
            shifted_copy(base, path, number * step)
        paths.append(path)
    return paths


def largest_tile(paths: list[Path], tile_size: float = 50.0) -> tuple[int, int, int]:
    """(tiles, core points of the largest, occupied cells) of the plan for the union of the files."""
    xyz = np.concatenate([np.column_stack([las.x, las.y, las.z]) for las in map(laspy.read, paths)])
    grid = DensityGrid.covering(xyz.min(0), xyz.max(0), tile_size)
    plan = plan_tiles(grid, *grid.count([xyz]), max_points=MAX_TILE_POINTS)
    return len(plan.tiles), max(t.count for t in plan.tiles), len(plan.cells)


def run(paths: list[Path], method: str, out: Path) -> Measured:
    command = [sys.executable, "-m", "pipeline.apps.cli", "run", *map(str, paths), "--ratio", "0.1", "-o", str(out),
               "--method", method, "--workers", "2", "--overwrite"]
    result = measure(command)
    if result.returncode != 0:
        sys.exit(f"failed: {' '.join(command)}\n{result.stderr}")
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--copies", type=int, default=10)
    parser.add_argument("--points", default="300k", help="points per copy")
    parser.add_argument("--spacing-km", type=float, default=10.0)
    parser.add_argument("--methods", default="fps,learned")
    parser.add_argument("--data", type=Path, default=Path(tempfile.gettempdir()) / "lidar-simplify-extent")
    args = parser.parse_args()
    points = parse_count(args.points)
    args.data.mkdir(parents=True, exist_ok=True)
    base = args.data / f"street_{points}.laz"
    if not base.exists():
        write_street_scan(base, n_points=points, seed=0)
    with laspy.open(base) as reader:
        width = float(reader.header.maxs[0] - reader.header.mins[0])
    layouts = {"compact": width + 10.0, "spread": args.spacing_km * 1000.0}
    print(f"{args.copies} copies of a {points:,}-point street scan ({width:.0f} m long): compact (side by side) "
          f"and spread ({args.spacing_km:g} km apart, {(args.copies - 1) * args.spacing_km:g} km end to end)")
    print("| layout | method | points | tiles | largest tile | occupied cells | wall s | points/s | peak RSS MiB |")
    print("| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    measured: dict[tuple[str, str], Measured] = {}
    with tempfile.TemporaryDirectory(dir=args.data) as out_dir:
        for name, step in layouts.items():
            paths = layout(base, args.copies, step, args.data / f"{name}-{args.copies}-{points}-{step:g}")
            tiles, largest, cells = largest_tile(paths)
            for method in args.methods.split(","):
                result = measured[name, method] = run(paths, method, Path(out_dir) / f"{name}-{method}.laz")
                total = points * args.copies
                print(f"| {name} | {method} | {total:,} | {tiles} | {largest:,} | {cells:,} | {result.seconds:.1f} | "
                      f"{total / result.seconds:,.0f} | {result.peak_rss_bytes / 2**20:,.0f} |", flush=True)
    for method in args.methods.split(","):
        compact, spread = measured["compact", method], measured["spread", method]
        print(f"{method}: peak RSS spread / compact = {spread.peak_rss_bytes / compact.peak_rss_bytes:.2f} "
              f"(target <= 1.2); wall spread / compact = {spread.seconds / compact.seconds:.2f} (target <= 1.2)")


if __name__ == "__main__":
    main()
