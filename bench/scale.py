"""Scaling of `pipeline run` with scan size and workers: wall time, points/s and peak RSS of the tree.

    python bench/scale.py [--sizes 1M,4M,16M,30M] [--methods learned,fps] [--workers 2] [--ratio 0.1]
                          [--one-worker-size 16M] [--data DIR]
    python bench/scale.py --sizes 1M,100M --one-worker-size 1M   # the 100M-point proof (issue 11)

Makes synthetic street scans with the project's simulator (streamed to LAZ in 500k-point chunks,
never whole in memory; kept in --data between runs), runs each method on each, then the one-worker
run at --one-worker-size for the speed-up. Every size runs on a local Dask cluster (`in_process_points = 0`),
so the memory check compares like with like: by default a scan up to 3M points runs on threads of one
process, whose tree is smaller than a cluster's, and one up to 21M in it too when `fps`'s, `voxel`'s or
`learned`'s tiles go to worker processes (`--in-process` keeps that default). Prints a Markdown table, each
run's phases (`-v`), the disk it used (input, work folder at its largest, output) and the three checks:
peak RSS flat (largest scan within 1.2x of the smallest), per-point cost within 1.2x from the smallest scan
to the largest, and 2 workers >= 1.7x one worker.
"""
from __future__ import annotations

import argparse
import re
import sys
import tempfile
import time
from pathlib import Path

from proctree import Measured, measure

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from pipeline.simulate import write_street_scan  # noqa: E402

SUMMARY = re.compile(r"of ([\d,]+) points \((\d+) tiles, ([\d.]+) s")
PHASES = re.compile(r"^(?:[a-z ]+: [\d.]+ s\s*)+$", re.MULTILINE)


def parse_count(text: str) -> int:
    """'4M' -> 4_000_000, '500k' -> 500_000, '1234' -> 1234."""
    units = {"k": 10**3, "m": 10**6}
    text = text.strip().lower()
    return int(float(text[:-1]) * units[text[-1]]) if text[-1] in units else int(text)


def scan_of(size: int, data: Path) -> Path:
    """The simulated scan of `size` points, made once."""
    path = data / f"street_{size}.laz"
    if not path.exists():
        started = time.perf_counter()
        write_street_scan(path, n_points=size, seed=0)
        print(f"simulated {size:,} points in {time.perf_counter() - started:.1f} s -> {path}", flush=True)
    return path


CLUSTER_CONFIG = "cluster.toml"  # written once into the output folder: every size on a local cluster


def run(scan: Path, method: str, workers: int, ratio: float, out_dir: Path, in_process: bool) -> Measured:
    """One `pipeline run` of the scan, measured over its process tree: on a local cluster whatever its size,
    unless `in_process` (then small scans run on threads, as by default)."""
    command = [sys.executable, "-m", "pipeline.apps.cli", "run", str(scan), "--ratio", str(ratio), "-o",
               str(out_dir / f"{scan.stem}-{method}-{workers}.laz"), "--method", method, "--workers", str(workers),
               "--overwrite", "-v", "--scratch", str(out_dir / "scratch")]
    if not in_process:
        command += ["--config", str(out_dir / CLUSTER_CONFIG)]
    (out_dir / "scratch").mkdir(exist_ok=True)
    result = measure(command, watch_folder=out_dir / "scratch")
    if result.returncode != 0:
        sys.exit(f"failed: {' '.join(command)}\n{result.stderr}")
    return result


def row(size: int, method: str, workers: int, result: Measured, scan: Path, out_dir: Path) -> str:
    own = float(SUMMARY.search(result.stdout).group(3))
    output = out_dir / f"{scan.stem}-{method}-{workers}.laz"
    return (f"| {method} | {workers} | {size:,} | {result.seconds:.1f} | {size / result.seconds:,.0f} "
            f"| {1e6 * result.seconds / size:.2f} | {own:.1f} | {result.peak_rss_bytes / 2**20:,.0f} "
            f"| {scan.stat().st_size / 2**20:,.0f} | {result.peak_folder_bytes / 2**20:,.0f} "
            f"| {output.stat().st_size / 2**20:,.0f} |")


def phases(size: int, method: str, workers: int, result: Measured) -> str:
    """The run's own phase times (`pipeline run -v`), one line."""
    found = PHASES.search(result.stdout)
    return f"{method}, {workers} worker(s), {size:,} points: {found.group(0).strip() if found else '?'}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", default="1M,4M,16M,30M")
    parser.add_argument("--methods", default="learned,fps")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--ratio", type=float, default=0.1)
    parser.add_argument("--one-worker-size", default="16M", help="size of the one-worker run for the speed-up")
    parser.add_argument("--data", type=Path, default=Path(tempfile.gettempdir()) / "lidar-simplify-scale")
    parser.add_argument("--in-process", action="store_true",
                        help="let scans under the in-process limit run on threads (default: every size on a cluster)")
    args = parser.parse_args()
    sizes = [parse_count(s) for s in args.sizes.split(",")]
    args.data.mkdir(parents=True, exist_ok=True)
    results: dict[tuple[str, int, int], Measured] = {}
    lines, phase_lines = [], []
    with tempfile.TemporaryDirectory(dir=args.data) as out_dir:
        (Path(out_dir) / CLUSTER_CONFIG).write_text("[run]\nin_process_points = 0\n")
        runs = [(size, method, args.workers) for size in sizes for method in args.methods.split(",")]
        runs += [(parse_count(args.one_worker_size), method, 1) for method in args.methods.split(",")]
        for size, method, workers in runs:
            scan = scan_of(size, args.data)
            results[method, workers, size] = run(scan, method, workers, args.ratio, Path(out_dir), args.in_process)
            lines.append(row(size, method, workers, results[method, workers, size], scan, Path(out_dir)))
            phase_lines.append(phases(size, method, workers, results[method, workers, size]))
            print(lines[-1], "\n" + phase_lines[-1], flush=True)
        one_size = parse_count(args.one_worker_size)
    print(f"\nratio {args.ratio}; wall = the whole command; us/pt = wall microseconds per input point; "
          f"own = the pipeline's own seconds; RSS = peak summed over the process tree; scratch = the work "
          f"folder at its largest (the tile store, surveys and tile results)")
    print("| method | workers | points | wall s | points/s | us/pt | own s | peak RSS MiB | input MiB | scratch MiB "
          "| output MiB |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    print("\n".join(lines))
    print("\nPhases (s):\n" + "\n".join(f"- {line}" for line in phase_lines))
    print()
    for method in args.methods.split(","):
        small, large = sizes[0], sizes[-1]
        rss = results[method, args.workers, large].peak_rss_bytes / results[method, args.workers, small].peak_rss_bytes
        cost = (results[method, args.workers, large].seconds / large) / (results[method, args.workers, small].seconds / small)
        speedup = results[method, 1, one_size].seconds / results[method, args.workers, one_size].seconds \
            if (method, args.workers, one_size) in results else float("nan")
        print(f"{method}: peak RSS {large:,} / {small:,} = {rss:.2f} (target <= 1.2); per-point cost "
              f"{large:,} / {small:,} = {cost:.2f} (target <= 1.2); {args.workers} workers / 1 worker at "
              f"{one_size:,} = {speedup:.2f}x (target >= 1.7)")


if __name__ == "__main__":
    main()
