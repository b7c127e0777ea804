"""Where the time goes: `pipeline run` per method, worker count and phase, beside CloudCompare and Open3D.

    python bench/throughput.py [--inputs bcts,lone-star,street,autzen] [--data DIR] [--ratio 0.1]
                               [--repeat 1] [--methods learned,fps,voxel,random] [--skip-open3d]

Inputs: `bcts` (bcts_1..4 together, 2.83 M airborne points), `lone-star` (519k terrestrial points, run with
--allow-geographic: its CRS label says WGS 84), `street` (a 1M-point simulated mobile street, written once
into a temporary folder), `autzen` (autzen_trim.laz, 110k points). Per input, one Markdown table:
each method with 1 and 2 workers (the phases `-v` prints as columns), CloudCompare's `-SS SPATIAL d` on
the points written once as PLY (d searched untimed, and cached, to keep ratio x N points) and `fps` and
`voxel` at 2 workers on that same PLY (the issue's like-for-like comparison: no LAZ to decode), Open3D's
voxel_down_sample and farthest_point_down_sample (O(N*M): only on up to 600k points), then one row per
target with "met" or "missed". Wall time is the whole command (imports, reading, writing), best of
--repeat (slowest in brackets), with Python's bytecode cache allowed as for an installed package; RSS is
the peak summed over the process tree (Dask workers included).
"""
from __future__ import annotations

import argparse
import json
import os
import re
import sys
import tempfile
from dataclasses import dataclass, replace
from importlib.util import find_spec
from pathlib import Path
from typing import Callable

import laspy
import numpy as np

import cloudcompare_peer
from proctree import Measured, measure

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))  # the PLY rows read the run's settings (pipeline.config) without an install
DEFAULT_DATA = HERE.parents[1] / "shared" / "data" / "lidar"
INPUTS = ("bcts", "lone-star", "street", "autzen")
METHODS = ("learned", "fps", "voxel", "random")
STREET_POINTS, STREET_SEED = 1_000_000, 3
OPEN3D_FPS_MAX = 600_000  # Open3D's FPS on bcts_1's 532k points takes about 45 s here; on 2.83M, 20 minutes
DISTANCE_CACHE = Path(tempfile.gettempdir()) / "lidar-simplify-bench" / "cloudcompare-distances.json"
SUMMARY = re.compile(r"([\d,]+) of ([\d,]+) points \(")
PHASES = ("start cluster", "read and bucket", "simplify tiles", "stitch and write")
PHASE = re.compile(rf"({'|'.join(PHASES)}): ([\d.]+) s")
COLUMNS = ("what", "workers", "points", "kept", "wall s", "points/s (wall)", *(f"{p} s" for p in PHASES),
           "rest s", "peak RSS MiB", "target")


@dataclass(frozen=True)
class Scan:
    """One input: its files and the options `pipeline run` needs for it."""

    name: str
    paths: tuple[Path, ...]
    options: tuple[str, ...] = ()


@dataclass(frozen=True)
class Timed:
    """One table row: the best of the runs of one command (`phases`: ours from `-v`, or a library call's own
    time in the simplify column; the rest of the wall time is imports, validation, loading and shutdown)."""

    what: str
    workers: str
    points: int
    kept: int
    seconds: float
    slowest: float
    rss_bytes: int
    phases: tuple[float | None, ...] = (None,) * len(PHASES)

    def row(self) -> str:
        timed = [p for p in self.phases if p is not None]
        rest = f"{self.seconds - sum(timed):.2f}" if timed else ""
        return cells(self.what, self.workers, f"{self.points:,}", f"{self.kept:,}",
                     f"{self.seconds:.2f} ({self.slowest:.2f})", f"{self.points / self.seconds:,.0f}",
                     *("" if p is None else f"{p:.2f}" for p in self.phases), rest, f"{self.rss_bytes / 2**20:,.0f}", "")


@dataclass(frozen=True)
class Target:
    """A ratio the issue sets a bound on: met when `value` is at most `limit` (or at least, if `floor`)."""

    what: str
    value: float
    limit: float
    floor: bool = False

    def row(self) -> str:
        met = self.value >= self.limit if self.floor else self.value <= self.limit
        value, limit = (f"{x:,.0f}" if x >= 1000 else f"{x:.2f}" for x in (self.value, self.limit))
        return cells(self.what, *[""] * (len(COLUMNS) - 2),
                     f"{value} ({'≥' if self.floor else '≤'} {limit}): {'met' if met else 'missed'}")


def cells(*values: str) -> str:
    """One Markdown table row."""
    return "| " + " | ".join(values) + " |"


def best(command: list[str], repeat: int) -> tuple[Measured, float]:
    """The fastest of `repeat` runs (the minimum is the least disturbed: this machine's speed drifts by
    up to 1.7x over minutes) and the slowest run's wall time, so the spread is visible."""
    runs = [measure(command) for _ in range(repeat)]
    for run in runs:
        if run.returncode != 0:
            sys.exit(f"failed: {' '.join(command)}\n{run.stderr}")
    return min(runs, key=lambda run: run.seconds), max(run.seconds for run in runs)


def scan_of(name: str, data: Path, work: Path) -> Scan | None:
    """The input called `name`, the street written into `work` first; None (with the reason printed) if missing."""
    if name == "street":
        from pipeline.simulate import write_street_scan

        path = work / "street.laz"
        write_street_scan(path, STREET_POINTS, seed=STREET_SEED)
        return Scan(name, (path,))
    files = {"bcts": [f"bcts_{i}.laz" for i in range(1, 5)], "lone-star": ["lone-star.laz"],
             "autzen": ["autzen_trim.laz"]}[name]
    paths = tuple(data / file for file in files)
    missing = [path for path in paths if not path.exists()]
    if missing:
        print(f"\nskipped {name}: {missing[0]} is missing (pass --data)")
        return None
    return Scan(name, paths, ("--allow-geographic",) if name == "lone-star" else ())


def pipeline_row(scan: Scan, method: str, workers: int, ratio: float, out_dir: Path, repeat: int) -> Timed:
    """`pipeline run -v` on the scan, with the phases it prints."""
    command = [sys.executable, "-m", "pipeline.apps.cli", "run", *map(str, scan.paths), *scan.options, "--ratio",
               str(ratio), "-o", str(out_dir / f"{method}-{workers}.laz"), "--method", method, "--workers",
               str(workers), "--overwrite", "-v"]
    run, slowest = best(command, repeat)
    kept, points = (int(n.replace(",", "")) for n in SUMMARY.search(run.stdout).groups())
    phases = dict(PHASE.findall(run.stdout))
    return Timed(f"pipeline run -m {method}", str(workers), points, kept, run.seconds, slowest, run.peak_rss_bytes,
                 tuple(float(phases[p]) if p in phases else None for p in PHASES))


def open3d_row(operation: str, paths: tuple[Path, ...], ratio: float, repeat: int) -> Timed:
    """Open3D's call in a child process (its own time in the simplify column), its voxel-size search taken off."""
    run, slowest = best([sys.executable, str(HERE / "open3d_peer.py"), operation, str(ratio), *map(str, paths)],
                        repeat)
    result = json.loads(run.stdout.strip().splitlines()[-1])
    search = result["search_seconds"]
    name = "voxel_down_sample" if operation == "voxel" else "farthest_point_down_sample"
    return Timed(f"Open3D {name} ({', '.join(p.name for p in paths)})", "1 process", result["points"],
                 result["kept"], run.seconds - search, slowest - search, run.peak_rss_bytes, (None, None, result["seconds"], None))


def open3d_rows(scan: Scan, ratio: float, repeat: int) -> list[Timed]:
    """Open3D's voxel grid on the scan, and its FPS on the scan, or its first file, if either is small enough."""
    fps_paths = next((scan.paths[:n] for n in (len(scan.paths), 1)
                      if sum(laspy.open(p).header.point_count for p in scan.paths[:n]) <= OPEN3D_FPS_MAX), None)
    rows = [open3d_row("voxel", scan.paths, ratio, repeat)]
    if fps_paths is None:
        print(f"skipped Open3D farthest_point_down_sample: over {OPEN3D_FPS_MAX:,} points", flush=True)
    else:
        rows.append(open3d_row("fps", fps_paths, ratio, 1))
    return rows


def cached_distance(key: str, find: Callable[[], float]) -> float:
    """CloudCompare's distance for `key` from the cache file, or found by `find()` and stored there."""
    cache = json.loads(DISTANCE_CACHE.read_text()) if DISTANCE_CACHE.exists() else {}
    if key not in cache:
        cache[key] = find()
        DISTANCE_CACHE.parent.mkdir(parents=True, exist_ok=True)
        DISTANCE_CACHE.write_text(json.dumps(cache, indent=1))
    return cache[key]


def as_ply(scan: Scan, work: Path) -> tuple[Path, np.ndarray]:
    """The scan's points written once (untimed) as the PLY CloudCompare reads, and its (n, 3) xyz."""
    xyz = np.concatenate([np.column_stack([las.x, las.y, las.z]) for las in map(laspy.read, scan.paths)])
    source = work / f"{scan.name}.ply"
    cloudcompare_peer.write_ply(xyz, source)
    return source, xyz


def cloudcompare_row(scan: Scan, ply: tuple[Path, np.ndarray], ratio: float, work: Path, repeat: int) -> Timed:
    """CloudCompare's spatial subsampling on the scan's PLY (d searched untimed)."""
    (source, xyz), result = ply, work / f"{scan.name}-cc.ply"
    key = f"{scan.name}:{len(xyz)}:{ratio:g}"
    distance = cached_distance(key, lambda: cloudcompare_peer.spatial_distance(source, xyz, ratio * len(xyz), result))
    run, slowest = best(cloudcompare_peer.command(source, distance, result), repeat)
    return Timed(f"CloudCompare -SS SPATIAL {distance:.4g}", "1 process", len(xyz),
                 cloudcompare_peer.kept_count(result), run.seconds, slowest, run.peak_rss_bytes)


def unit_options(scan: Scan) -> tuple[str, ...]:
    """Length options that give the scan's PLY (no CRS, so metres are assumed) the tiles its LAS files get in
    their own unit (autzen is in feet: 50 m tiles are 164 ft there, not 50)."""
    from pipeline.config import RunConfig
    from pipeline.io.points import length_unit_of

    metres = length_unit_of(scan.paths[0]).metres  # 1 for metres and degrees: nothing to convert
    if metres == 1.0:
        return ()
    lengths = RunConfig().in_unit(metres)
    return ("--tile-size", repr(lengths.tile_size), "--overlap", repr(lengths.overlap),
            "--seam-tolerance", repr(lengths.seam_tolerance))


def same_file_rows(scan: Scan, source: Path, methods: list[str], ratio: float, work: Path,
                   repeat: int) -> dict[str, Timed]:
    """`fps` and `voxel` (of `methods`) at 2 workers on the very PLY CloudCompare reads, as the issue timed them:
    a PLY holds no LAZ to decode, so these rows, not the LAZ ones, are the like-for-like comparison."""
    rows, ply = {}, Scan(scan.name, (source,), unit_options(scan))
    for method in (m for m in ("fps", "voxel") if m in methods):
        timed = pipeline_row(ply, method, 2, ratio, work, repeat)
        rows[method] = replace(timed, what=f"{timed.what} (on CloudCompare's PLY)")
    return rows


def targets(scan: Scan, ours: dict[tuple[str, int], Timed], peer: Timed | None, bcts_cost: float | None,
            same_file: dict[str, Timed]) -> list[Target]:
    """The issue's targets this input's rows can be checked against (2 workers unless said)."""
    found = []
    for method in ("fps", "voxel"):
        if peer is not None and method in same_file:
            found.append(Target(f"{method} wall / CloudCompare wall, the same PLY", same_file[method].seconds / peer.seconds,
                                1.0))
        if peer is not None and (method, 2) in ours:
            found.append(Target(f"{method} wall on the LAZ / CloudCompare wall on the PLY",
                                ours[method, 2].seconds / peer.seconds, 1.0))
    learned = ours.get(("learned", 2))
    if learned is not None and scan.name == "bcts":
        found.append(Target("learned points/s (wall)", learned.points / learned.seconds, 500_000, floor=True))
        found.append(Target("learned points/s (wall), issue 10's floor", learned.points / learned.seconds, 250_000,
                            floor=True))
    if learned is not None and bcts_cost is not None and scan.name in ("lone-star", "street"):
        found.append(Target("learned s per point / bcts's", learned.seconds / learned.points / bcts_cost, 1.5))
    for (method, workers), one in ours.items():
        if workers == 1 and (method, 2) in ours:
            found.append(Target(f"{method} speed, 2 workers / 1", one.seconds / ours[method, 2].seconds, 1.9,
                                floor=True))
    if scan.name == "autzen":
        found += [Target(f"{m} wall s", ours[m, 2].seconds, 1.5) for m in ("fps", "learned") if (m, 2) in ours]
    return found


def bench_scan(scan: Scan, args: argparse.Namespace, work: Path, bcts_cost: float | None) -> float | None:
    """Print the scan's table; return learned's 2-worker seconds per point (for the other inputs' targets)."""
    print(f"\n### {scan.name} ({', '.join(p.name for p in scan.paths)})\n")
    print(cells(*COLUMNS))
    print(cells(*["---"] + ["---:"] * (len(COLUMNS) - 1)), flush=True)
    ours: dict[tuple[str, int], Timed] = {}
    for method in args.methods.split(","):
        for workers in (1, 2):
            ours[method, workers] = pipeline_row(scan, method, workers, args.ratio, work, args.repeat)
            print(ours[method, workers].row(), flush=True)
    if args.skip_open3d or find_spec("open3d") is None:
        print("skipped Open3D: --skip-open3d or not installed (pip install -e '.[bench]')", flush=True)
    else:
        for row in open3d_rows(scan, args.ratio, args.repeat):
            print(row.row(), flush=True)
    peer, same_file = None, {}
    if cloudcompare_peer.available():
        ply = as_ply(scan, work)
        peer = cloudcompare_row(scan, ply, args.ratio, work, args.repeat)
        same_file = same_file_rows(scan, ply[0], args.methods.split(","), args.ratio, work, args.repeat)
    print(peer.row() if peer else "skipped CloudCompare: not on PATH (Debian's cloudcompare)", flush=True)
    for row in same_file.values():
        print(row.row(), flush=True)
    for target in targets(scan, ours, peer, bcts_cost, same_file):
        print(target.row(), flush=True)
    learned = ours.get(("learned", 2))
    return learned.seconds / learned.points if learned else None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--inputs", default="bcts", help=f"comma-separated, of {', '.join(INPUTS)}")
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="folder holding the shared scans")
    parser.add_argument("--ratio", type=float, default=0.1)
    parser.add_argument("--repeat", type=int, default=1, help="runs per row; the fastest is reported")
    parser.add_argument("--methods", default=",".join(METHODS), help="comma-separated pipeline methods to run")
    parser.add_argument("--skip-open3d", action="store_true")
    args = parser.parse_args()
    # as an installed package runs: Python may cache its bytecode (an environment that forbids writing it, as
    # this machine's does, re-compiles the project's ~100 modules on every run: 0.3-0.4 s of a small one)
    os.environ.pop("PYTHONDONTWRITEBYTECODE", None)
    names = args.inputs.split(",")
    if unknown := set(names) - set(INPUTS):
        sys.exit(f"unknown input {sorted(unknown)[0]}: choose from {', '.join(INPUTS)}")
    print(f"ratio {args.ratio}, best of {args.repeat}; wall = whole command (imports, read, write), slowest run in "
          f"brackets; phases as `pipeline run -v` prints them (Open3D: its call's own time under simplify); RSS = "
          f"peak summed over the process tree; targets at 2 workers unless said")
    bcts_cost = None
    with tempfile.TemporaryDirectory() as tmp:
        for name in sorted(names, key=INPUTS.index):  # bcts first: the others' per-point cost is set against it
            scan = scan_of(name, args.data, Path(tmp))
            if scan is not None:
                cost = bench_scan(scan, args, Path(tmp), bcts_cost)
                bcts_cost = cost if name == "bcts" else bcts_cost


if __name__ == "__main__":
    main()
