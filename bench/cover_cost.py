"""What the hole cover costs the curvature error (CE), and why: the stratified fill with and without it.

    python bench/cover_cost.py [--scans bcts_1.laz,lone-star.laz,autzen_trim.laz,street] [--ratio 0.1]
                               [--out bench/results]

Each scan is one tile (no tiling, so nothing but the cover differs). The fill is model.stratified's even
fill along the Morton curve (equal weights); the cover is its greedy set cover of the points farther than
COVER_SPACINGS typical spacings from the fill (model.stratified.hole_cover), h picks, the fill giving up h
so the count stays round(ratio x N). Rows: the fill of the whole count; the fill of the count less h alone
(what giving up h costs); that fill plus the cover; plus h points drawn at random among the points the
cover serves (far from the fill: is it where the cover puts them, or that they are in sparse places?); plus
h points drawn among the others (more points, elsewhere). For each: CE, the 99th-percentile and the
largest scan-to-kept distance, and the mean curvature the fill's own points show in the kept cloud (the
cover's points enter their neighbourhoods). Writes cover_cost.md under --out.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from quality import DEFAULT_DATA, load_scan, xyz_of  # noqa: E402

from model.geometry import nearest_distance, point_features  # noqa: E402
from model.metrics import feature_error, nearest  # noqa: E402
from model.rules import kept_count  # noqa: E402
from model.selection import Tile  # noqa: E402
from model.stratified import (COVER_SPACINGS, filled_and_covered, hole_cover, systematic_picks,  # noqa: E402
                              typical_spacing)


def scored(xyz: np.ndarray, curvature: np.ndarray, kept: np.ndarray, fill: int) -> tuple[float, float, float, float]:
    """CE, p99 and largest scan-to-kept distance of `kept` (its first `fill` the fill's points), and the
    mean curvature those fill points show in the kept cloud."""
    kept_curvature = point_features(xyz[kept]).mean_curvature
    match = nearest(xyz[kept], xyz)
    distance = np.sqrt(match.sq_dist)
    return (feature_error(curvature, kept_curvature, match.index), float(np.quantile(distance, 0.99)),
            float(distance.max()), float(kept_curvature[:fill].mean()))


def cover_rows(name: str, xyz: np.ndarray, ratio: float) -> list[str]:
    """Markdown rows of the five selections of the module doc for one scan."""
    tile = Tile(xyz, np.ones(len(xyz), dtype=bool), np.zeros(3), seed=0)
    count = kept_count(ratio, len(xyz))
    whole = systematic_picks(tile.curve, count, 0.5)
    radius = COVER_SPACINGS * typical_spacing(xyz[whole])
    fill, cover = filled_and_covered(tile, lambda picks: systematic_picks(tile.curve, picks, 0.5), count, radius,
                                     len(hole_cover(xyz, whole, np.arange(len(xyz)), radius, tile.curve)))
    rest = np.setdiff1d(np.arange(len(xyz)), fill)
    served = rest[nearest_distance(xyz[fill], xyz[rest]) > radius]
    others = np.setdiff1d(rest, np.concatenate([served, cover]))
    rng = np.random.default_rng(0)
    top_up = rng.choice(others, count - len(fill) - len(cover), replace=False)  # as the pipeline tops up
    others = np.setdiff1d(others, top_up)
    h = len(cover)
    selections = {  # the kept points, the fill's first
        "the fill of the whole count": whole,
        f"the fill less the cover's h = {h:,} and the top-up": fill,
        "that fill + the cover + the top-up (stratified)": np.concatenate([fill, cover, top_up]),
        "that fill + h points the cover serves, at random, + the top-up": np.concatenate(
            [fill, rng.choice(served, min(h, len(served)), replace=False), top_up]),
        "that fill + h other points, at random, + the top-up": np.concatenate(
            [fill, rng.choice(others, h, replace=False), top_up]),
    }
    curvature = point_features(xyz).mean_curvature
    rows = []
    for label, kept in selections.items():
        ce, p99, largest, fill_curvature = scored(xyz, curvature, kept, count if kept is whole else len(fill))
        rows.append(f"| {name} | {label} | {len(kept):,} | {ce:.5f} | {p99:.4g} | {largest:.4g} "
                    f"| {fill_curvature:.4f} |")
        print(rows[-1], flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scans", default="bcts_1.laz,lone-star.laz,autzen_trim.laz,street")
    parser.add_argument("--ratio", type=float, default=0.1)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--out", type=Path, default=HERE / "results")
    args = parser.parse_args()
    lines = ["# What the hole cover costs CE", "",
             f"Made by `python bench/cover_cost.py --scans {args.scans} --ratio {args.ratio:g}`: each scan one tile; "
             "see the script's docstring for the rows.", "",
             "| scan | kept | points | CE | p99 | largest distance | fill points' mean curvature in the kept cloud |",
             "| --- | --- | ---: | ---: | ---: | ---: | ---: |"]
    with tempfile.TemporaryDirectory(prefix="cover-cost-") as work:
        for scan in args.scans.split(","):
            _, las = load_scan(scan, args.data, Path(work))
            xyz = xyz_of(las)
            lines += cover_rows(Path(scan).stem, xyz - xyz.mean(axis=0), args.ratio)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "cover_cost.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
