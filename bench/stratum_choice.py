"""Which point of each stratum the fill keeps: the default's fixed place against choosing by position or curvature.

    python bench/stratum_choice.py [--scans bcts_1.laz,street] [--ratios 0.1] [--radii 1.5,1.75]

The default's fill (model.stratified.weighted_picks) cuts a Morton curve into strata of unit keep probability
and keeps the point at a fixed place (the phase) of each. This asks whether another choice within the same
strata (the same density pattern) moves issue 10's frontier: `central` keeps the point nearest its stratum's
probability-weighted mean position (evener spacing), `max-kappa` its most curved point (the scan's own 16-point
curvature). Each scan as one tile with the default's weights and hole cover at fixed radii (multiples of FPS's
p99), scored as bench/frontier.py scores (CE over random's, p99 and Chamfer over FPS's). Then the step-and-pole
scene of tests/test_detail.py, for what each choice keeps of a 90-degree edge and a pole at the fill's count
and at half of it (the share left to the fill where the hole cover takes the rest). Prints Markdown tables.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Callable

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from frontier import covered, one_tile  # noqa: E402
from quality import DEFAULT_DATA  # noqa: E402

from model.detail import predicted_fill_loss  # noqa: E402
from model.geometry import point_features  # noqa: E402
from model.stratified import curve_of, keep_probabilities, keep_weights, weighted_picks  # noqa: E402

MAX_POINTS = 600_000  # a scan is cut to its middle this many points (the metrics' kNN over millions is slow here)
Chooser = Callable[[np.ndarray, np.ndarray, np.ndarray | None, int], np.ndarray]


def strata(weights: np.ndarray | None, count: int, points: int) -> tuple[np.ndarray, np.ndarray]:
    """(points,) keep probabilities along the curve and each point's stratum: unit runs of probability centred on
    weighted_picks' crossings at phase 0.5 (a point by its middle), the ends joined to the first and last."""
    chance = keep_probabilities(np.ones(points) if weights is None else weights, count)
    middle = np.cumsum(chance) - chance / 2
    return chance, np.clip(np.floor(middle), 0, count - 1).astype(np.int64)


def best_of_strata(curve: np.ndarray, stratum: np.ndarray, score: np.ndarray) -> np.ndarray:
    """The curve's point of lowest finite `score` (curve order) in each stratum (strata ascend along the curve)."""
    opens = np.concatenate([[True], stratum[1:] != stratum[:-1]])
    run = np.cumsum(opens) - 1
    best = np.minimum.reduceat(score, np.flatnonzero(opens))
    at = np.flatnonzero((score == best[run]) & np.isfinite(score))
    return curve[at[np.concatenate([[True], run[at][1:] != run[at][:-1]])]]


def central(xyz: np.ndarray, curve: np.ndarray, weights: np.ndarray | None, count: int) -> np.ndarray:
    """Each stratum's point nearest its probability-weighted mean position (a point kept surely stays)."""
    chance, stratum = strata(weights, count, len(curve))
    points = xyz[curve]
    mass = np.maximum(np.bincount(stratum, chance, minlength=count), np.finfo(float).tiny)
    centre = np.column_stack([np.bincount(stratum, chance * points[:, a], minlength=count) for a in range(3)])
    offset = points - (centre / mass[:, None])[stratum]
    score = np.einsum("ij,ij->i", offset, offset)
    return best_of_strata(curve, stratum, np.where(chance <= 0, np.inf, np.where(chance >= 1, -1.0, score)))


def most_curved(kappa: np.ndarray) -> Chooser:
    """Each stratum's point of highest curvature kappa (n,)."""
    def choose(xyz: np.ndarray, curve: np.ndarray, weights: np.ndarray | None, count: int) -> np.ndarray:
        chance, stratum = strata(weights, count, len(curve))
        return best_of_strata(curve, stratum, np.where(chance <= 0, np.inf, -kappa[curve]))
    return choose


def choosers(kappa: np.ndarray) -> dict[str, Chooser]:
    return {"systematic (default)": lambda xyz, curve, weights, count: weighted_picks(curve, weights, count, 0.5),
            "central": central, "max-kappa": most_curved(kappa)}


def frontier_rows(scan: str, ratio: float, radii: list[float], data: Path, work: Path) -> None:
    """Prints a row per chooser and radius: CE over random's, p99 and Chamfer over FPS's, the scan as one tile."""
    scene = one_tile(scan, ratio, data, work, MAX_POINTS)
    curve = scene.tile.curve
    weights = curve_of(keep_weights(scene.tile, scene.loss, 1.0), curve)
    for name, choose in choosers(scene.features.kappa).items():
        for multiple in radii:
            kept = covered(scene.tile, lambda n: choose(scene.xyz, curve, weights, n), scene.count,
                           multiple * scene.fps["p99"])
            row = scene.row(scan, ratio, name, multiple, scene.score(kept))
            print(f"| {scan} | {ratio:g} | {name} | {multiple:g} | {row['ce']:.3f} | {row['p99']:.3f} | "
                  f"{row['cd']:.3f} |", flush=True)


def crease_rows() -> None:
    """Prints what each choice keeps of the step edge and the pole of tests/test_detail.py's scene (seeds 0-3),
    with equal weights and with the default's, at the fill's count at 0.1 and at half of it."""
    sys.path.insert(0, str(HERE.parent / "tests"))
    from test_detail import edge_pole_plane

    for seed in range(4):
        tile, near_edge, on_pole = edge_pole_plane(seed)
        count = round(0.1 * len(tile.xyz))
        loss = predicted_fill_loss(tile, count)
        kappa = point_features(tile.xyz).kappa
        for strength in (0.0, 1.0):
            weights = curve_of(keep_weights(tile, loss, strength), tile.curve) if strength else None
            for picks in (count, count // 2):
                kept = {name: choose(tile.xyz, tile.curve, weights, picks) for name, choose in choosers(kappa).items()}
                print(f"| {seed} | {strength:g} | {picks} | "
                      + " | ".join(f"{int(near_edge[k].sum())} / {int(on_pole[k].sum())}" for k in kept.values())
                      + " |", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--scans", default="bcts_1.laz,street,lone-star.laz,autzen_trim.laz,"
                                            "las_with_several_extra_byte_bloc.laz,airborne")
    parser.add_argument("--ratios", default="0.2,0.1,0.05")
    parser.add_argument("--radii", default="1.5,1.75", help="hole radii, in FPS's p99")
    parser.add_argument("--work", type=Path, default=Path("/tmp/frontier-work"))
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    print("| scan | ratio | choice | radius | CE / random | p99 / FPS | CD / FPS |\n" + "|" + " --- |" * 7)
    for ratio in map(float, args.ratios.split(",")):
        for scan in args.scans.split(","):
            frontier_rows(scan, ratio, [float(r) for r in args.radii.split(",")], args.data, args.work)
    print("\n| seed | detail | fill picks | " + " | ".join(f"{name}: edge / pole" for name in choosers(np.empty(0)))
          + " |\n" + "|" + " --- |" * 6)
    crease_rows()


if __name__ == "__main__":
    main()
