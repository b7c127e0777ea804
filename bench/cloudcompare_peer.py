"""CloudCompare's spatial subsampling (`-SS SPATIAL d`) as a peer, run as users run Debian's `cloudcompare`.

Debian's build reads PLY, not LAS, so the points are written once as a binary PLY; the minimum distance
`d` that keeps a wanted count is searched by running the command itself (a secant on log count against
log d, which converges in a few runs because the kept count falls as a power of d).
"""
from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyElement

ENV = ("env", "QT_QPA_PLATFORM=offscreen")  # no display: Qt's offscreen platform
MAX_RUNS = 12


def available() -> bool:
    """Whether the `CloudCompare` command is on PATH."""
    return shutil.which("CloudCompare") is not None


def write_ply(xyz: np.ndarray, path: Path) -> None:
    """Write the points, centred and as float32 (CloudCompare's own precision), as a binary PLY."""
    local = (xyz - xyz.mean(axis=0)).astype(np.float32)
    vertex = np.empty(len(local), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    vertex["x"], vertex["y"], vertex["z"] = local.T
    PlyData([PlyElement.describe(vertex, "vertex")], text=False).write(str(path))


def command(source: Path, distance: float, result: Path) -> list[str]:
    """The command line a user runs: open the PLY, subsample at `distance`, save only the result as PLY."""
    return [*ENV, "CloudCompare", "-SILENT", "-AUTO_SAVE", "OFF", "-O", str(source), "-SS", "SPATIAL",
            f"{distance:.6g}", "-C_EXPORT_FMT", "PLY", "-SAVE_CLOUDS", "FILE", str(result)]


def kept_count(result: Path) -> int:
    """Points in a PLY CloudCompare wrote (its header only is read)."""
    with result.open("rb") as handle:
        for line in handle:
            if line.startswith(b"element vertex"):
                return int(line.split()[2])
    raise ValueError(f"no vertex count in {result}")


def run_once(source: Path, distance: float, result: Path) -> int:
    """Run the subsampling once (untimed) and return how many points it kept."""
    result.unlink(missing_ok=True)
    subprocess.run(command(source, distance, result), check=True, capture_output=True, timeout=900)
    return kept_count(result)


def spatial_distance(source: Path, xyz: np.ndarray, target: float, result: Path, tolerance: float = 0.01) -> float:
    """The distance at which `source` (holding `xyz`) keeps `target` points within `tolerance` (or the closest of
    MAX_RUNS tries); the first guess is the spacing of `target` points spread evenly over the bounding box."""
    extent = np.sort(np.ptp(xyz, axis=0))[1:]  # the two longest sides: airborne xy, terrestrial any
    distance, slope = float(np.sqrt(np.prod(extent) / target)), -2.0  # kept ~ d^-2 on a surface
    tried: list[tuple[float, int]] = []
    for _ in range(MAX_RUNS):
        kept = run_once(source, distance, result)
        tried.append((distance, kept))
        if abs(kept - target) <= tolerance * target:
            return distance
        if len(tried) > 1 and tried[-2][1] != kept:
            slope = np.log(tried[-2][1] / kept) / np.log(tried[-2][0] / distance)
        step = np.exp(np.log(target / max(kept, 1)) / min(slope, -0.5))
        distance *= float(np.clip(step, 0.25, 4.0))
    return min(tried, key=lambda t: abs(t[1] - target))[0]
