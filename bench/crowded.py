"""Memory bounded by --max-tile-points on a terrestrial standpoint, where one grid cell holds millions.

    python bench/crowded.py [--points 3M] [--limits 200000,50000] [--methods fps,learned] [--data DIR]

Simulates one scanner standpoint (points thinning with range, 70 % ground and 30 % walls to 4 m, the
densest 6.25 m grid cell holding about a third of them), then runs `pipeline run` (2 workers) at each
`--max-tile-points`, measured over the process tree. The plan splits every cell over the limit on its
sub-cells, so the largest tile and what a task holds follow the limit, not the standpoint, and the
tree's peak is set by the other settings (bucketing pieces, the chunk cache). Prints the plan's largest
tile and largest core plus `--overlap` halo (what a `learned` task holds) beside wall and peak.
"""
from __future__ import annotations

import argparse
import re
import sys
import tempfile
from pathlib import Path

import laspy
import numpy as np
from proctree import measure

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from scale import parse_count  # noqa: E402
from tiling.plan import DensityGrid, crowded_cells, plan_tiles  # noqa: E402

SUMMARY = re.compile(r"of ([\d,]+) points \((\d+) tiles, ([\d.]+) s")
TILE_SIZE = 50.0
OVERLAP = 2.0


def write_standpoint(path: Path, points: int, seed: int = 0) -> None:
    """A scanner at (1000, 2000): ranges drawn from a gamma law (dense near the scanner), 70 % ground with
    2 cm noise, 30 % wall points up to 4 m; millimetre LAS 1.4."""
    rng = np.random.default_rng(seed)
    distance = rng.gamma(1.5, 2.0, points) + 0.5
    azimuth = rng.uniform(0, 2 * np.pi, points)
    header = laspy.LasHeader(version="1.4", point_format=6)
    header.scales, header.offsets = [0.001] * 3, [1000.0, 2000.0, 0.0]
    las = laspy.LasData(header)
    las.x, las.y = 1000 + distance * np.cos(azimuth), 2000 + distance * np.sin(azimuth)
    las.z = np.where(rng.random(points) < 0.7, 0.02 * rng.normal(size=points), rng.uniform(0, 4, points))
    las.write(path)


def plan_extremes(path: Path, limit: int) -> tuple[int, int, int]:
    """(tiles, core points of the largest, largest core plus halo) of the run's plan at `limit`."""
    las = laspy.read(path)
    xyz = np.column_stack([las.x, las.y, las.z])
    grid = DensityGrid.covering(xyz.min(0), xyz.max(0), TILE_SIZE)
    cells, counts = grid.count([xyz])
    plan = plan_tiles(grid, cells, counts, limit, grid.sub_count(xyz, crowded_cells(cells, counts, limit)))
    seen = [int(plan.halo_mask(plan.core_mask(t, xyz), t, xyz, OVERLAP).sum()) for t in range(len(plan.tiles))]
    return len(plan.tiles), max(t.count for t in plan.tiles), max(seen)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--points", default="3M")
    parser.add_argument("--limits", default="200000,50000", help="--max-tile-points values to run")
    parser.add_argument("--methods", default="fps,learned")
    parser.add_argument("--data", type=Path, default=None, help="keep the simulated scan here (default: a temp dir)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as temporary:
        folder = args.data or Path(temporary)
        folder.mkdir(parents=True, exist_ok=True)
        scan = folder / f"standpoint-{args.points}.laz"
        if not scan.exists():
            write_standpoint(scan, parse_count(args.points))
        print("| max tile points | method | tiles | largest tile | largest core+halo | wall s | peak RSS MiB |")
        print("| ---: | --- | ---: | ---: | ---: | ---: | ---: |")
        for limit in (int(value) for value in args.limits.split(",")):
            tiles, largest, held = plan_extremes(scan, limit)
            for method in args.methods.split(","):
                command = [sys.executable, "-m", "pipeline.apps.cli", "run", str(scan), "--ratio", "0.1", "-o",
                           str(Path(temporary) / "out.laz"), "--method", method, "--workers", "2", "--overwrite",
                           "--max-tile-points", str(limit), "--tile-size", str(TILE_SIZE), "--overlap", str(OVERLAP)]
                result = measure(command)
                if result.returncode != 0:
                    sys.exit(f"failed: {' '.join(command)}\n{result.stderr}")
                ran = SUMMARY.search(result.stdout + result.stderr)
                print(f"| {limit:,} | {method} | {ran.group(2) if ran else tiles} | {largest:,} | {held:,} | "
                      f"{result.seconds:.1f} | {result.peak_rss_bytes / 2**20:.0f} |")


if __name__ == "__main__":
    main()
