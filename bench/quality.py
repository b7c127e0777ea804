"""Where each method keeps points, and what that costs: the table issue 10 decides by, with pictures.

    python bench/quality.py [--scans autzen_trim.laz,street] [--ratios 0.2,0.1,0.05]
                            [--methods learned,stratified,fps,random,voxel] [--peer] [--out bench/results]
                            [--name quality] [--config FILE]

For each scan and ratio, every method runs through `pipeline.run` (tiled, 2 workers, one cluster),
and so does FPS over the whole scan as one tile ("fps untiled", the coverage reference) and, with
--peer, CloudCompare's spatial subsampling at the same count (its minimum distance searched, then
the surplus dropped at random; Debian's `cloudcompare`). Each result is scored against the whole scan
with every metric of model.metrics.quality and the 99th percentile of the scan-to-result distance.
Pictures (PNG, under --out/quality/): per scan, a kept-to-expected density map per method (points
kept per cell over ratio x points there, cells of ~100 scan points at the median; grey: under one expected) and, on the simulated
streets, close-ups of a sign, a pole, a car and a kerb per method. The simulated streets are `street` (a car's
mobile scan) and `airborne` (the same street flown over at 80 m; not among the defaults), each another street
with `:SEED` after its name (`street:7`: the simulator's scene and drive from seed 7, not 3): on them every label
(and the simulator's finer parts: kerb, window, sign) is scored on its own: share of its points kept, and the
99th-percentile distance from its points to the nearest kept point, beside FPS's. Writes quality.md and
quality.json.
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path

import laspy
import numpy as np
from matplotlib.colors import TwoSlopeNorm
from matplotlib.figure import Figure

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from model import Tile  # noqa: E402
from model.baselines import fps_simplify  # noqa: E402
from model.geometry import point_features  # noqa: E402
from model.metrics import nearest, quality  # noqa: E402
from pipeline.config import build_config  # noqa: E402
from pipeline.engine.execute import cluster  # noqa: E402
from pipeline.engine.runner import run_scan  # noqa: E402
from pipeline.simulate import LABELS, PARTS, surface_parts, write_street_scan  # noqa: E402
from model.rules import kept_count  # noqa: E402

DEFAULT_DATA = HERE.parents[1] / "shared" / "data" / "lidar"
SCANS = ("bcts_1.laz", "bcts_2.laz", "bcts_3.laz", "bcts_4.laz", "autzen_trim.laz", "lone-star.laz",
         "las_with_several_extra_byte_bloc.laz", "street")
STREET_POINTS, STREET_SEED = 600_000, 3
SIMULATED = {"street": "mobile", "airborne": "airborne"}  # scan name -> simulator platform (both STREET_POINTS)
METHODS = ("learned", "stratified-detail", "stratified", "paper", "fps", "random", "voxel")
UNTILED, PEER = "fps untiled", "cloudcompare spatial"
CELL_POINTS = 100  # scan points per density-map cell, on average over occupied cells
STRUCTURE = ("building", "window", "kerb", "pole", "sign", "car", "utility_line")


@dataclass(frozen=True)
class Row:
    """One method on one scan at one ratio."""

    scan: str
    ratio: float
    method: str
    points: int
    chamfer: float
    hausdorff: float
    p99: float
    curvature_error: float
    roughness_error: float
    sdm: float
    normal_consistency: float


def simulated(name: str) -> tuple[str, int] | None:
    """The simulator platform and seed of a simulated scan's name (`street`, `airborne`, either with `:SEED`);
    None for a file's name."""
    base, colon, seed = name.partition(":")
    if base not in SIMULATED:
        return None
    if colon and not seed.isdigit():
        raise SystemExit(f"{name}: a simulated scan's seed is a whole number (street:7)")
    return SIMULATED[base], int(seed) if colon else STREET_SEED


def file_stem(name: str) -> str:
    """A scan's name as a file name's stem (street:7 -> street-s7)."""
    return Path(name.replace(":", "-s")).stem


def load_scan(name: str, data: Path, work: Path) -> tuple[Path, laspy.LasData]:
    """The scan's path and its points (a simulated street is written once into `work`)."""
    street = simulated(name)
    if street is not None:
        path = work / f"{file_stem(name)}.las"
        if not path.exists():
            platform, seed = street
            write_street_scan(path, STREET_POINTS, seed=seed, platform=platform)
    else:
        path = data / name
    return path, laspy.read(path)


def xyz_of(las: laspy.LasData) -> np.ndarray:
    """(n, 3) float64 coordinates."""
    return np.column_stack([las.x, las.y, las.z]).astype(np.float64)


def untiled_fps(xyz: np.ndarray, count: int) -> np.ndarray:
    """Indices of FPS over the whole scan as one tile."""
    tile = Tile(xyz - xyz.mean(axis=0), np.ones(len(xyz), dtype=bool), np.zeros(3), seed=0)
    return fps_simplify(tile, count).indices


def cloudcompare_spatial(xyz: np.ndarray, count: int, work: Path) -> np.ndarray:
    """Indices of CloudCompare's `-SS SPATIAL d` result, d searched so it keeps at least `count`, surplus
    dropped at random (seeded). CloudCompare reads PLY here; its points are matched back by position."""
    from plyfile import PlyData

    from cloudcompare_peer import run_once, spatial_distance, write_ply

    source, result = work / "cc_in.ply", work / "cc_out.ply"
    write_ply(xyz, source)
    run_once(source, spatial_distance(source, xyz, count * 1.005, result, tolerance=0.005), result)
    kept = PlyData.read(str(result))["vertex"]
    kept_xyz = np.column_stack([kept["x"], kept["y"], kept["z"]]).astype(np.float64)
    index = np.unique(nearest(xyz - xyz.mean(axis=0), kept_xyz).index)
    return np.random.default_rng(0).permutation(index)[:count]


def score(scan: str, ratio: float, method: str, xyz: np.ndarray, kept: np.ndarray, features) -> Row:
    """Every metric of the kept points against the scan, and the 99th-percentile scan-to-kept distance."""
    q = quality(xyz, xyz[kept], features)
    p99 = float(np.sqrt(np.quantile(nearest(xyz[kept], xyz).sq_dist, 0.99)))
    return Row(scan, ratio, method, len(kept), q.chamfer, q.hausdorff, p99, q.curvature_error, q.roughness_error,
               q.sdm, q.normal_consistency)


def kept_indices(output: Path, las: laspy.LasData) -> np.ndarray:
    """Indices into the scan of an output's points (matched by their integer coordinates)."""
    out = laspy.read(output)
    scan_keys = np.column_stack([las.X, las.Y, las.Z]).astype(np.int64)
    out_keys = np.column_stack([out.X, out.Y, out.Z]).astype(np.int64)
    index = nearest(scan_keys.astype(np.float64), out_keys.astype(np.float64)).index
    return index


def density_map(scan: str, ratio: float, xyz: np.ndarray, picks: dict[str, np.ndarray], path: Path) -> Path:
    """A panel per method: log2 of (kept per cell) / (ratio x scan points per cell); white is 'as expected'."""
    low, high = xyz[:, :2].min(axis=0), xyz[:, :2].max(axis=0)
    side = float(np.sqrt(np.prod(np.maximum(high - low, 1e-9)) * CELL_POINTS / len(xyz)))
    for _ in range(4):  # so the median occupied cell holds about CELL_POINTS scan points
        _, per_cell = np.unique(np.floor((xyz[:, :2] - low) / side).astype(np.int64), axis=0, return_counts=True)
        side *= float(np.sqrt(CELL_POINTS / np.median(per_cell)))
    shape = np.maximum(np.ceil((high - low) / side).astype(int), 1)

    def counts(points: np.ndarray) -> np.ndarray:
        ij = np.minimum(np.floor((points[:, :2] - low) / side).astype(int), shape - 1)
        return np.bincount(ij[:, 0] * shape[1] + ij[:, 1], minlength=shape[0] * shape[1]).reshape(shape)

    expected = counts(xyz) * ratio
    panels = len(picks)
    aspect = shape[1] / shape[0]
    if aspect < 0.5:  # a long strip (a corridor, a flight line): panels one above the other, as wide as the page
        figure = Figure(figsize=(12.0, panels * (12.0 * aspect + 0.4) + 0.6), layout="constrained")
        axes = figure.subplots(panels, 1, squeeze=False)[:, 0]
    else:
        figure = Figure(figsize=(3.4 * panels, max(2.2, 3.4 * aspect) + 0.6), layout="constrained")
        axes = figure.subplots(1, panels, squeeze=False)[0]
    image = None
    for ax, (method, kept) in zip(axes, picks.items()):
        with np.errstate(divide="ignore", invalid="ignore"):  # an empty cell shows as -2 (a quarter or less)
            share = np.log2(np.maximum(counts(xyz[kept]), expected / 4) / expected)
        share[expected < 1] = np.nan  # cells expected to keep less than one point say nothing
        ax.set_facecolor("#cccccc")
        image = ax.imshow(share.T, origin="lower", cmap="RdBu_r", norm=TwoSlopeNorm(0, -2, 2), interpolation="nearest")
        ax.set_title(method, fontsize=9)
        ax.set_xticks([]), ax.set_yticks([])
    figure.colorbar(image, ax=list(axes), shrink=0.8, label="log2 kept / expected")
    figure.suptitle(f"{scan} at {ratio:g}: kept-to-expected density, cells of {side:.3g} units", fontsize=10)
    return save_small(figure, path, dpi=80)


def save_small(figure: Figure, path: Path, dpi: int) -> Path:
    """The figure as a 256-colour PNG: a third of the RGBA size, so the pictures can be committed."""
    from io import BytesIO

    from PIL import Image

    buffer = BytesIO()
    figure.savefig(buffer, dpi=dpi, format="png")
    Image.open(buffer).convert("RGB").quantize(256).save(path, optimize=True)
    return path


def street_labels(las: laspy.LasData, scan: str = "street") -> dict[str, np.ndarray]:
    """Label name -> mask of a simulated street's points: Toronto3D-style labels, then the finer parts."""
    label = np.asarray(las.user_data)
    masks = {name: label == code for code, name in LABELS.items() if (label == code).any()}
    street = simulated(scan)
    if street is None:
        raise ValueError(f"{scan} is not a simulated street: it has no labels")
    platform, seed = street
    parts = surface_parts(STREET_POINTS, seed, platform)
    masks.update({name: parts == code for code, name in PARTS.items()})
    return masks


def label_rows(scan: str, ratio: float, xyz: np.ndarray, masks: dict[str, np.ndarray],
               picks: dict[str, np.ndarray]) -> list[dict]:
    """Per label and method: share of the label's points kept, p99 distance from them to the nearest kept point."""
    rows = []
    for name, mask in masks.items():
        for method, kept in picks.items():
            distance = np.sqrt(nearest(xyz[kept], xyz[mask]).sq_dist)
            rows.append({"scan": scan, "ratio": ratio, "label": name, "method": method, "points": int(mask.sum()),
                         "share": float(np.isin(np.flatnonzero(mask), kept).sum() / mask.sum() / ratio),
                         "p99": float(np.quantile(distance, 0.99))})
    return rows


def object_view(ratio: float, xyz: np.ndarray, masks: dict[str, np.ndarray], picks: dict[str, np.ndarray],
                path: Path) -> Path:
    """Close-ups of one sign, pole, car and kerb stretch (side views of a 6 m box around each): the scan in
    the first row, each method below; the object's own points in colour, everything else grey."""
    objects = [name for name in ("sign", "pole", "car", "kerb") if masks.get(name, np.zeros(1, bool)).any()]
    rows = {"scan": np.arange(len(xyz)), **picks}
    figure = Figure(figsize=(3.0 * len(objects), 1.9 * len(rows)), layout="constrained")
    axes = figure.subplots(len(rows), len(objects), squeeze=False)
    for column, name in enumerate(objects):
        members = np.flatnonzero(masks[name])
        centre = xyz[members[len(members) // 2]]  # one object: a point of it, and its surroundings
        box = np.all(np.abs(xyz[:, :2] - centre[:2]) < 3.0, axis=1)
        for row, (title, index) in enumerate(rows.items()):
            ax = axes[row, column]
            inside = index[box[index]]
            own = inside[masks[name][inside]]
            size = 0.4 if title == "scan" else 3.0
            ax.scatter(xyz[inside, 0], xyz[inside, 2], s=size, c="#bbbbbb", linewidths=0)
            ax.scatter(xyz[own, 0], xyz[own, 2], s=size * 1.5, c="#d62728", linewidths=0)
            ax.set_aspect("equal")
            ax.set_xticks([]), ax.set_yticks([])
            ax.set_title(f"{name}: {title} ({len(own)} of its points)", fontsize=7)
    return save_small(figure, path, dpi=80)


def run_bench(scans: list[str], ratios: list[float], methods: list[str], peer: bool, data: Path, out: Path,
              name: str = "quality", config: str | None = None) -> None:
    """Run everything, print and write the tables, draw the pictures; `config`: a preset or TOML file the
    pipeline runs take their settings from (as `pipeline run --config`)."""
    pictures = out / "quality"
    pictures.mkdir(parents=True, exist_ok=True)
    rows: list[Row] = []
    labels: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="quality-") as tmp, cluster(2, "2GB", None) as client:
        work = Path(tmp)
        for scan in scans:
            path, las = load_scan(scan, data, work)
            xyz = xyz_of(las)
            xyz -= xyz.mean(axis=0)
            features = point_features(xyz)
            for ratio in ratios:
                count = kept_count(ratio, len(xyz))
                picks: dict[str, np.ndarray] = {}
                for method in methods:
                    output = work / f"{method}.las"
                    run_scan([path], output, build_config(config, ratio=ratio, method=method, workers=2), overwrite=True,
                             client=client)
                    picks[method] = kept_indices(output, las)
                picks[UNTILED] = untiled_fps(xyz, count)
                if peer and shutil.which("CloudCompare"):
                    picks[PEER] = cloudcompare_spatial(xyz, count, work)
                for method, kept in picks.items():
                    rows.append(score(scan, ratio, method, xyz, kept, features))
                    print(format_row(rows[-1]), flush=True)
                stem = f"{file_stem(scan)}-{ratio:g}"
                density_map(scan, ratio, xyz, picks, pictures / f"density-{stem}.png")
                if simulated(scan):
                    masks = street_labels(las, scan)
                    labels += label_rows(scan, ratio, xyz, masks, picks)
                    object_view(ratio, xyz, masks, picks, pictures / f"objects-{stem}.png")
    (out / f"{name}.json").write_text(json.dumps({"rows": [asdict(r) for r in rows], "labels": labels}, indent=1))
    (out / f"{name}.md").write_text(markdown(rows, labels))
    print(markdown(rows, labels))


def format_row(r: Row) -> str:
    return (f"{r.scan:38s} {r.ratio:<5g} {r.method:22s} {r.points:8d} CD {r.chamfer:.4g} H {r.hausdorff:.4g} "
            f"p99 {r.p99:.4g} CE {r.curvature_error:.5f} RE {r.roughness_error:.5f} SDM {r.sdm:.4f} "
            f"NC {r.normal_consistency:.4f}")


def markdown(rows: list[Row], labels: list[dict]) -> str:
    """The metric table with each value's ratio to the best baseline (CE/RE/SDM) or to untiled FPS (CD, p99)."""
    command = " ".join(["python bench/quality.py", *sys.argv[1:]])
    lines = [f"# Quality per method\n\nMade by `{command}` (2 workers, every point scored; p99: 99th percentile "
             "of the scan-to-result distance; lower is better everywhere).\n",
             "| scan | ratio | method | CD | Hausdorff | p99 | CE | RE | SDM | NC | CD / untiled FPS | "
             "p99 / untiled FPS | CE / best baseline |", "|" + " --- |" * 13]
    for r in rows:
        group = [g for g in rows if g.scan == r.scan and g.ratio == r.ratio]
        untiled = next(g for g in group if g.method == UNTILED)
        baselines = [g for g in group if g.method in ("random", "fps", "voxel", PEER, UNTILED)]
        best_ce = min(g.curvature_error for g in baselines) if baselines else float("nan")
        lines.append(f"| {r.scan} | {r.ratio:g} | {r.method} | {r.chamfer:.4g} | {r.hausdorff:.4g} | {r.p99:.4g} | "
                     f"{r.curvature_error:.5f} | {r.roughness_error:.5f} | {r.sdm:.4f} | {r.normal_consistency:.4f} | "
                     f"{r.chamfer / untiled.chamfer:.2f} | {r.p99 / untiled.p99:.2f} | {r.curvature_error / best_ce:.2f} |")
    if labels:
        lines += ["", "Simulated streets' labels: share kept (1 = the ratio's share) and p99 distance from the label's "
                  "points to the nearest kept point (m).", "",
                  "| scan | ratio | label | points | method | share | p99 | p99 / FPS (tiled) |", "|" + " --- |" * 8]
        for row in labels:
            fps = next((x for x in labels if x["scan"] == row["scan"] and x["ratio"] == row["ratio"]
                        and x["label"] == row["label"] and x["method"] == "fps"), None)
            to_fps = (f"{row['p99'] / fps['p99']:.2f}" if fps and fps["p99"] > 0  # fps not among --methods, or
                      else "—")                                              # every point of a tiny label kept
            lines.append(f"| {row['scan']} | {row['ratio']:g} | {row['label']} | {row['points']:,} | {row['method']} | "
                         f"{row['share']:.2f} | {row['p99']:.3f} | {to_fps} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--scans", default=",".join(SCANS))
    parser.add_argument("--ratios", default="0.2,0.1,0.05")
    parser.add_argument("--methods", default=",".join(METHODS))
    parser.add_argument("--peer", action="store_true", help="add CloudCompare's spatial subsampling (Debian cloudcompare)")
    parser.add_argument("--out", type=Path, default=HERE / "results")
    parser.add_argument("--name", default="quality", help="stem of the .md and .json written to --out")
    parser.add_argument("--config", default=None, help="preset or TOML file for the pipeline runs (as pipeline run --config)")
    args = parser.parse_args()
    run_bench(args.scans.split(","), [float(r) for r in args.ratios.split(",")], args.methods.split(","),
              args.peer, args.data, args.out, args.name, args.config)


if __name__ == "__main__":
    main()
