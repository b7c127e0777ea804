"""How closely the tiles alone can stand for one farthest point sampling (FPS) of the whole scan: the reference
the default's coverage bounds are held against (its Chamfer bound, model/chamfer_bound.py; issue 10 measures p99
and Chamfer against an untiled FPS).

    python bench/fps_reference.py [--scans airborne,street,lone-star.laz,bcts_1.laz,autzen_trim.laz]
                                  [--ratios 0.1] [--data ../shared/data/lidar] [--out bench/results]

For each scan and ratio, on the tiles a default `learned` run plans (tiling.plan, as bench/seams.py plans them):
- "at shares": each tile's FPS at its share of the count, the Chamfer bound's reference until 0.3.12;
- "one radius": each tile's FPS run on to one covering radius r* for the whole scan, the radius at which the tiles'
  counts add up to the target (a tile past its share where it must, up to MAX_SHARE_MULTIPLE times), as one pass
  over the whole scan covers everywhere at about one radius: what a run measures since 0.3.12
  (pipeline/engine/covers.py, which counts a tile past its share as far as r* asks).
For each, the p99 and the mean squared distance from an even sample of each tile's core (model.chamfer_bound's
sample) to the tile's picks, pooled by core points, over the same of an untiled FPS (every point scored). Writes
fps_reference.md under --out.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from quality import DEFAULT_DATA, load_scan, untiled_fps, xyz_of  # noqa: E402
from seams import run_plan  # noqa: E402

from model.chamfer_bound import core_sample  # noqa: E402
from model.cover import cover_order, insertion_radii  # noqa: E402
from model.geometry import nearest_distance  # noqa: E402
from model.rules import kept_count  # noqa: E402
from tiling.budgets import pooled_quantile  # noqa: E402
from pipeline import PipelineNote  # noqa: E402

MAX_SHARE_MULTIPLE = 4  # how far past its share a tile's sampling runs
RADIUS_STEPS = 40  # bisection steps for r*


class TileCurve:
    """One tile's core (c, 3), centred, its share of the count, and its FPS order up to MAX_SHARE_MULTIPLE x the share
    with the covering radius after each pick (non-increasing)."""

    def __init__(self, core: np.ndarray, share: int) -> None:
        self.core = core - core.mean(axis=0)
        self.share = share
        order = cover_order(self.core, min(len(core), max(MAX_SHARE_MULTIPLE * share, 16)))
        _, first = np.unique(order, return_index=True)
        self.order = order[np.sort(first)]
        self.radii = np.minimum.accumulate(insertion_radii(self.core, self.order))
        self.sample = core_sample(self.core)

    def picks_at(self, radius: float) -> int:
        """Picks that cover the core at `radius` (all sampled, if they do not)."""
        return max(1, int(np.searchsorted(-self.radii, -radius, side="left")))

    def short_at(self, radius: float) -> bool:
        """Whether the sampled picks fall short of covering the core at `radius`."""
        return len(self.order) < len(self.core) and self.radii[-1] > radius

    def distances(self, picks: int) -> np.ndarray:
        """The sample's distances to the first `picks` picks."""
        return nearest_distance(self.core[self.order[:picks]], self.sample)


def one_radius(curves: list[TileCurve], target: int) -> float:
    """r*: the smallest radius at which the tiles' counts add up to at most `target` (bisection in log radius)."""
    def total(radius: float) -> int:
        return sum(curve.picks_at(radius) for curve in curves)
    high = max(float(curve.radii[1]) for curve in curves if len(curve.radii) > 1)  # one pick each, or fewer
    if total(high) > target:
        raise SystemExit(f"{len(curves)} tiles need more than the {target} points kept to have one each")
    low = high
    while total(low) <= target and low > 1e-12:
        low /= 2
    for _ in range(RADIUS_STEPS):
        middle = float(np.sqrt(low * high))
        low, high = (middle, high) if total(middle) > target else (low, middle)
    return high


def pooled(curves: list[TileCurve], picks: list[int]) -> tuple[float, float]:
    """p99 and mean squared distance of the tiles' samples to their first `picks`, each sample standing for its
    tile's core points."""
    distance = [curve.distances(count) for curve, count in zip(curves, picks)]
    cores = np.array([len(curve.core) for curve in curves])
    msq = float(sum(size * np.mean(d ** 2) for size, d in zip(cores, distance)) / cores.sum())
    return pooled_quantile(distance, cores, 0.99), msq


def measure(scan: str, ratio: float, data: Path, work: Path) -> str:
    """One markdown row: the two references over an untiled FPS."""
    _, las = load_scan(scan, data, work)
    xyz = xyz_of(las)
    target = kept_count(ratio, len(xyz))
    tiles = run_plan(las, xyz, "learned", ratio).tile_of(xyz[:, :2])
    curves = [TileCurve(xyz[tiles == tile], kept_count(ratio, int((tiles == tile).sum())))
              for tile in np.unique(tiles)]
    radius = one_radius(curves, target)
    untiled = nearest_distance(xyz[untiled_fps(xyz, target)], xyz)
    fps_p99, fps_msq = float(np.quantile(untiled, 0.99)), float(np.mean(untiled ** 2))
    share_p99, share_msq = pooled(curves, [max(curve.share, 1) for curve in curves])
    one_p99, one_msq = pooled(curves, [curve.picks_at(radius) for curve in curves])
    short = sum(curve.short_at(radius) for curve in curves)
    row = (f"| {scan} | {ratio:g} | {len(curves)} | {share_p99 / fps_p99:.3f} | {share_msq / fps_msq:.3f} | "
           f"{one_p99 / fps_p99:.3f} | {one_msq / fps_msq:.3f} | {radius / fps_p99:.3f} | {short} |")
    print(row, flush=True)
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scans", default="airborne,street,lone-star.laz,bcts_1.laz,autzen_trim.laz")
    parser.add_argument("--ratios", default="0.1")
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--out", type=Path, default=HERE / "results")
    args = parser.parse_args()
    warnings.simplefilter("ignore", PipelineNote)  # a foot scan's unit note
    head = ["| scan | ratio | tiles | at shares: p99 | at shares: mean sq. | one radius: p99 | one radius: mean sq. | "
            "r* / FPS's p99 | tiles short of r* |", "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    print("\n".join(head), flush=True)
    rows = []
    with tempfile.TemporaryDirectory(prefix="fps-reference-") as work:  # where a simulated street is written
        for scan in args.scans.split(","):
            for ratio in (float(r) for r in args.ratios.split(",")):
                rows.append(measure(scan, ratio, args.data, Path(work)))
    command = " ".join(["python bench/fps_reference.py", *sys.argv[1:]])
    text = (f"# Standing in for one FPS of the whole scan\n\nMade by `{command}`. Each column over an untiled FPS's "
            "same figure (p99 and mean squared scan-to-result distance); see the script's docstring.\n\n"
            + "\n".join(head + rows) + "\n")
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "fps_reference.md").write_text(text)


if __name__ == "__main__":
    main()
