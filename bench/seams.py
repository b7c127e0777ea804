"""How much a tiled run's output shows its tile seams: the share of points kept at each distance from the
nearest point of another tile, over the output's share, per method (1 everywhere: no seam to see).

    python bench/seams.py [--scans las_with_several_extra_byte_bloc.laz,bcts_1.laz,lone-star.laz,autzen_trim.laz]
                          [--ratio 0.1] [--methods learned,fps,stratified,random] [--data ../shared/data/lidar]

Why: a density map of an output (bench/quality.py's pictures) shows faint lines along tile borders where a
method packs its picks there; this puts a number on them. Each method runs as `pipeline run` would (2 workers);
the tile plan is planned again from the scan's points with the run's settings (tiling.plan, the same
functions the run calls); distances are in the output's median spacing (nearest kept neighbour), bands of
half a spacing to eight. A band with 2.0 keeps twice its share: one method's row of picks along each border.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import warnings
from pathlib import Path

import laspy
import numpy as np
from pykdtree.kdtree import KDTree

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from quality import DEFAULT_DATA, kept_indices, load_scan, xyz_of  # noqa: E402

import pipeline  # noqa: E402
from pipeline import PipelineNote  # noqa: E402
from pipeline.config import build_config  # noqa: E402
from pipeline.io.crs import length_unit  # noqa: E402
from tiling.plan import DensityGrid, TilePlan, crowded_cells, plan_tiles  # noqa: E402

BANDS = (0.0, 0.5, 1.0, 2.0, 4.0, 8.0, np.inf)  # band edges, in output spacings from the nearest other tile


def run_plan(las: laspy.LasData, xyz: np.ndarray, method: str, ratio: float) -> TilePlan:
    """The tile plan a default run of `method` makes of the scan (header bounds, lengths in the scan's unit)."""
    config = build_config(None, ratio=ratio, method=method).in_unit(length_unit(las.header).metres)
    grid = DensityGrid.covering(np.asarray(las.header.mins), np.asarray(las.header.maxs), config.tile_size)
    cells, counts = grid.count([xyz[:, :2]])
    crowded = crowded_cells(cells, counts, config.max_tile_points)
    sub_counts = grid.sub_count(xyz[:, :2], crowded) if len(crowded) else None
    return plan_tiles(grid, cells, counts, config.max_tile_points, sub_counts, config.merge_limit)


def seam_distance(xy: np.ndarray, tiles: np.ndarray, reach: float) -> np.ndarray:
    """(n,) each point's XY distance to the nearest point of another tile, up to `reach` (inf beyond)."""
    distance = np.full(len(xy), np.inf)
    for tile in np.unique(tiles):
        inside = np.flatnonzero(tiles == tile)
        low, high = xy[inside].min(axis=0) - reach, xy[inside].max(axis=0) + reach
        near = np.flatnonzero((tiles != tile) & np.all((xy >= low) & (xy <= high), axis=1))
        if len(near):
            found, _ = KDTree(np.ascontiguousarray(xy[near])).query(np.ascontiguousarray(xy[inside]), k=1,
                                                                    distance_upper_bound=reach)
            distance[inside] = found
    return distance


def bands(seam: np.ndarray, spacing: float) -> list[np.ndarray]:
    """(n,) masks of the points in each band of BANDS (x `spacing`); the last holds those past its start."""
    return [(seam >= low * spacing) & ((seam < high * spacing) | (high == np.inf))
            for low, high in zip(BANDS[:-1], BANDS[1:])]


def profile(kept: np.ndarray, seam: np.ndarray, spacing: float) -> list[tuple[float, float]]:
    """Per band: the kept share over the output's (nan for an empty band) and the share of the scan's points."""
    share = kept.mean()
    return [(float(kept[band].mean() / share) if band.any() else float("nan"), float(band.mean()))
            for band in bands(seam, spacing)]


def measure(scan: str, ratio: float, methods: list[str], data: Path, work: Path) -> list[str]:
    """Markdown rows for one scan: a row per method."""
    path, las = load_scan(scan, data, work)
    xyz = xyz_of(las)
    centre = xyz.mean(axis=0)
    rows = []
    for method in methods:
        output = work / f"{Path(scan).stem}-{method}.laz"
        pipeline.run(path, output, ratio=ratio, method=method, overwrite=True)
        kept = np.zeros(len(xyz), dtype=bool)
        kept[kept_indices(output, las)] = True
        kept_xyz = xyz[kept] - centre
        spacing = float(np.median(KDTree(kept_xyz).query(kept_xyz, k=2)[0][:, 1]))
        tiles = run_plan(las, xyz, method, ratio).tile_of(xyz[:, :2])
        seam = seam_distance(xyz[:, :2] - centre[:2], tiles, BANDS[-2] * spacing)
        shares = profile(kept, seam, spacing)
        cells = " | ".join(f"{share:.2f} ({100 * part:.1f} %)" for share, part in shares)
        rows.append(f"| {scan} | {ratio:g} | {method} | {len(np.unique(tiles))} | {spacing:.3g} | {cells} |")
        print(rows[-1], flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scans", default="las_with_several_extra_byte_bloc.laz,bcts_1.laz,lone-star.laz,"
                                          "autzen_trim.laz")
    parser.add_argument("--ratio", type=float, default=0.1)
    parser.add_argument("--methods", default="learned,fps,stratified,random")
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    args = parser.parse_args()
    warnings.simplefilter("ignore", PipelineNote)  # a foot scan's unit note
    heads = " | ".join(f"[{low:g}, {high:g})" for low, high in zip(BANDS[:-1], BANDS[1:]))
    print(f"| scan | ratio | method | tiles | spacing | {heads} |")
    print("| --- | --- | --- | ---: | ---: |" + " ---: |" * (len(BANDS) - 1))
    with tempfile.TemporaryDirectory() as folder:
        for scan in args.scans.split(","):
            measure(scan, args.ratio, args.methods.split(","), args.data, Path(folder))


if __name__ == "__main__":
    main()
