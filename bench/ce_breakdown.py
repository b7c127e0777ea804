"""Where the curvature error (CE) is lost: each method's CE split by how curved the scan is at each point.

    python bench/ce_breakdown.py [--scans street,lone-star.laz,bcts_1.laz,autzen_trim.laz] [--ratio 0.1]
                                 [--methods learned,random,fps] [--out bench/results]

CE is the root mean square, over the scan's points, of the difference between a point's mean curvature
and that of its nearest kept point (model.metrics). This splits the mean square by bands of the scan's
own mean curvature (its quantiles, so every scan has the same bands: the flattest half, then up to the
80th, 90th, 95th, 99th percentile and the top 1 %), and on the simulated street by surface label. For
each band: the mean squared term per method, the mean curvature of the scan there and that of the
nearest kept points (a sparser cloud's neighbourhoods are wider: where they reach other surfaces, its
curvature comes out higher), and the band's part of the difference between the first two methods'
CE^2 (positive: the first method loses there; the parts add up to the difference). Writes ce_breakdown.md
under --out.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from quality import DEFAULT_DATA, kept_indices, load_scan, simulated, street_labels, xyz_of  # noqa: E402

from model.geometry import point_features  # noqa: E402
from model.metrics import nearest  # noqa: E402
from model.rules import kept_count  # noqa: E402
from pipeline.config import build_config  # noqa: E402
from pipeline.engine.execute import cluster  # noqa: E402
from pipeline.engine.runner import run_scan  # noqa: E402

BAND_EDGES = (0.5, 0.8, 0.9, 0.95, 0.99)  # quantiles of the scan's mean curvature between the bands


def band_names() -> list[str]:
    """'q0-50', 'q50-80', ... 'q99-100' for the bands BAND_EDGES cut."""
    edges = [0, *[round(100 * e) for e in BAND_EDGES], 100]
    return [f"q{low}-{high}" for low, high in zip(edges[:-1], edges[1:])]


def squared_terms(xyz: np.ndarray, reference_curvature: np.ndarray, kept: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(n,) each scan point's squared CE term against the kept points (n,) and the kept curvature it met."""
    kept_curvature = point_features(xyz[kept]).mean_curvature
    met = kept_curvature[nearest(xyz[kept], xyz).index]
    return np.square(reference_curvature - met), met


def breakdown_rows(scan: str, groups: dict[str, np.ndarray], reference: np.ndarray,
                   terms: dict[str, tuple[np.ndarray, np.ndarray]]) -> list[str]:
    """Markdown rows: per group, points, the scan's curvature, per method mean squared term and the
    curvature met, and the group's part of the difference between the first two methods' CE^2 (its
    summed terms' difference over all the scan's points, x 1e-5: the parts add up to the difference)."""
    methods = list(terms)
    first, second = methods[0], methods[1]
    rows = []
    for name, mask in groups.items():
        if not mask.any():
            continue
        cells = [scan, name, f"{int(mask.sum()):,}", f"{reference[mask].mean():.4f}"]
        cells += [f"{terms[m][0][mask].mean():.5f} / {terms[m][1][mask].mean():.4f}" for m in methods]
        part = float(terms[first][0][mask].sum() - terms[second][0][mask].sum()) / len(reference)
        rows.append("| " + " | ".join(cells + [f"{part * 1e5:+.1f}"]) + " |")
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--scans", default="street,lone-star.laz,bcts_1.laz,autzen_trim.laz")
    parser.add_argument("--ratio", type=float, default=0.1)
    parser.add_argument("--methods", default="learned,random,fps")
    parser.add_argument("--out", type=Path, default=HERE / "results")
    args = parser.parse_args()
    methods = args.methods.split(",")
    header = ("| scan | points by the scan's mean curvature | points | scan's curvature | "
              + " | ".join(f"{m}: mean sq. term / curvature met" for m in methods)
              + f" | part of {methods[0]} CE^2 - {methods[1]} CE^2, x 1e-5 |")
    lines = ["# Where the curvature error is lost", "",
             f"Made by `python bench/ce_breakdown.py --scans {args.scans} --ratio {args.ratio:g} --methods "
             f"{args.methods}` (2 workers, every point scored). See the script's docstring for the columns; "
             "the parts of each scan's band rows add up to the CE^2 difference, as do its label rows.", "",
             header, "| " + " | ".join(["---"] * (len(methods) + 5)) + " |"]
    summary: list[str] = []
    with tempfile.TemporaryDirectory(prefix="ce-") as tmp, cluster(2, "2GB", None) as client:
        work = Path(tmp)
        for scan in args.scans.split(","):
            path, las = load_scan(scan, args.data, work)
            xyz = xyz_of(las)
            xyz -= xyz.mean(axis=0)
            reference = point_features(xyz).mean_curvature
            terms = {}
            for method in methods:
                output = work / f"{method}.las"
                run_scan([path], output, build_config(None, ratio=args.ratio, method=method, workers=2),
                         overwrite=True, client=client)
                kept = kept_indices(output, las)
                assert len(kept) == kept_count(args.ratio, len(xyz))
                terms[method] = squared_terms(xyz, reference, kept)
            line = f"{scan}: CE " + ", ".join(f"{m} {np.sqrt(terms[m][0].mean()):.5f}" for m in methods)
            print(line, flush=True)
            summary.append(f"- {line}")
            band = np.digitize(reference, np.quantile(reference, BAND_EDGES))
            groups = {name: band == b for b, name in enumerate(band_names())}
            lines += breakdown_rows(scan, groups, reference, terms)
            if simulated(scan):
                lines += breakdown_rows(scan, street_labels(las, scan), reference, terms)
    args.out.mkdir(parents=True, exist_ok=True)
    lines += ["", *summary]
    (args.out / "ce_breakdown.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
