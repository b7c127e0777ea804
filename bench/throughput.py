"""Throughput and peak memory of `pipeline run` per method and worker count, beside Open3D.

    python bench/throughput.py [--data DIR] [--ratio 0.1] [--repeat 1]

Runs each method (learned, stratified, fps, voxel, random) with 1 and 2 workers on bcts_1..4 (2.83 M points, one scan in four files), then
Open3D's voxel_down_sample on the same points and farthest_point_down_sample on bcts_1 alone (Open3D's
FPS is O(N*M): on all 2.83 M points it would run for about 20 minutes here). Prints a Markdown table:
end-to-end wall time of the whole command (imports, reading, writing included), the pipeline's own
time, points/s on each, and the peak RSS summed over the process tree (Dask workers included).
"""
from __future__ import annotations

import argparse
import json
import re
import sys
import tempfile
from pathlib import Path

from proctree import Measured, measure

HERE = Path(__file__).resolve().parent
DEFAULT_DATA = HERE.parents[1] / "shared" / "data" / "lidar"
SUMMARY = re.compile(r"of ([\d,]+) points \((\d+) tiles, ([\d.]+) s")
METHODS = ("learned", "stratified", "fps", "voxel", "random")


def best(command: list[str], repeat: int) -> tuple[Measured, float]:
    """The fastest of `repeat` runs (the minimum is the least disturbed: this machine's speed drifts by
    up to 1.7x over minutes) and the slowest run's wall time, so the spread is visible."""
    runs = [measure(command) for _ in range(repeat)]
    for run in runs:
        if run.returncode != 0:
            sys.exit(f"failed: {' '.join(command)}\n{run.stderr}")
    return min(runs, key=lambda run: run.seconds), max(run.seconds for run in runs)


def pipeline_row(inputs: list[Path], method: str, workers: int, ratio: float, out_dir: Path, repeat: int) -> str:
    output = out_dir / f"{method}-{workers}.laz"
    command = [sys.executable, "-m", "pipeline.cli", "run", *map(str, inputs), "--ratio", str(ratio), "-o",
               str(output), "--method", method, "--workers", str(workers), "--overwrite"]
    run, slowest = best(command, repeat)
    points, tiles, own_seconds = SUMMARY.search(run.stdout).groups()
    n = int(points.replace(",", ""))
    return (f"| pipeline run --method {method} | {workers} | {n:,} | {run.seconds:.2f} ({slowest:.2f}) "
            f"| {n / run.seconds:,.0f} "
            f"| {float(own_seconds):.2f} | {n / float(own_seconds):,.0f} | {run.peak_rss_bytes / 2**20:,.0f} |")


def open3d_row(operation: str, inputs: list[Path], ratio: float, repeat: int) -> str:
    run, slowest = best([sys.executable, str(HERE / "open3d_peer.py"), operation, str(ratio), *map(str, inputs)],
                        repeat)
    result = json.loads(run.stdout.strip().splitlines()[-1])
    n, seconds = result["points"], result["seconds"]
    name = "voxel_down_sample" if operation == "voxel" else "farthest_point_down_sample"
    files = "bcts_1..4" if len(inputs) > 1 else inputs[0].name
    return (f"| Open3D {name} ({files}) | 1 process | {n:,} | {run.seconds:.2f} ({slowest:.2f}) "
            f"| {n / run.seconds:,.0f} "
            f"| {seconds:.2f} | {n / seconds:,.0f} | {run.peak_rss_bytes / 2**20:,.0f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="folder holding bcts_1..4.laz")
    parser.add_argument("--ratio", type=float, default=0.1)
    parser.add_argument("--repeat", type=int, default=1, help="runs per row; the fastest is reported")
    parser.add_argument("--methods", default=",".join(METHODS), help="comma-separated pipeline methods to run")
    parser.add_argument("--skip-open3d", action="store_true")
    args = parser.parse_args()
    inputs = [args.data / f"bcts_{i}.laz" for i in range(1, 5)]
    missing = [p for p in inputs if not p.exists()]
    if missing:
        sys.exit(f"missing input: {missing[0]} (pass --data)")
    print(f"ratio {args.ratio}, best of {args.repeat}; wall = whole command (imports, read, write), slowest "
          f"run in brackets; own = the pipeline's or the library call's own time; RSS = peak summed over the "
          f"process tree")
    print("| what | workers | points | wall s | points/s (wall) | own s | points/s (own) | peak RSS MiB |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    with tempfile.TemporaryDirectory() as out_dir:
        for method in args.methods.split(","):
            for workers in (1, 2):
                print(pipeline_row(inputs, method, workers, args.ratio, Path(out_dir), args.repeat), flush=True)
    if not args.skip_open3d:
        print(open3d_row("voxel", inputs, args.ratio, args.repeat), flush=True)
        print(open3d_row("fps", inputs[:1], args.ratio, 1), flush=True)


if __name__ == "__main__":
    main()
