"""CD, CE, RE and SDM of the learned simplifiers against FPS on the saved TOSCA test split (for the model card).

    python bench/tosca_eval.py [--weights model/learning/weights/tosca.pt] [--data DIR] [--ratios 0.2,0.1,0.05]
                               [--no-paper]

Each test mesh's vertices are simplified once per progressive method (FPS, the paper's network) at the
largest ratio; smaller ratios are prefixes of that priority order, as the pipeline would produce them.
The default `learned`, `stratified` and `random` run once per ratio. Prints a Markdown table of the
means over the test meshes (lower is better for all four). `--no-paper` leaves out the paper's four
variants (most of the run's time), to measure again what changed in the others.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from model import Tile, get_simplifier
from model.geometry import point_features
from model.learning import PAPER_WEIGHTS
from model.learned import learned_simplify
from model.meshes import list_meshes, load_mesh, mesh_name
from model.metrics import quality

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "meshes" / "tosca"
PER_RATIO = ("learned", "stratified", "random")  # not progressive: run at each ratio


def evaluate(vertices: np.ndarray, ratios: list[float], weights: Path | None) -> dict[tuple[str, float], np.ndarray]:
    """(method, ratio) -> [CD, CE, RE, SDM] for one mesh; the paper's network only with `weights`."""
    xyz = vertices - vertices.mean(axis=0)
    tile = Tile(xyz, np.ones(len(xyz), dtype=bool), np.zeros(3), seed=0)
    largest = int(round(max(ratios) * len(xyz)))
    orders = {"fps": get_simplifier("fps")(tile, largest)}
    for exact, selector in ((True, "exact"), (False, "8-d")) if weights is not None else ():
        for refine, moved in ((True, "refined"), (False, "unmoved")):
            orders[f"paper ({selector} latent FPS, {moved})"] = learned_simplify(tile, largest, weights, exact=exact,
                                                                                 refine=refine)
    reference = point_features(xyz)
    scores = {}
    for ratio in ratios:
        count = int(round(ratio * len(xyz)))
        kept = {method: selection.xyz[:count] for method, selection in orders.items()}
        kept.update({method: get_simplifier(method)(tile, count).xyz for method in PER_RATIO})
        for method, points in kept.items():
            q = quality(xyz, points, reference)
            scores[(method, ratio)] = np.array([q.chamfer, q.curvature_error, q.roughness_error, q.sdm])
    return scores


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--weights", type=Path, default=PAPER_WEIGHTS)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--ratios", default="0.2,0.1,0.05")
    parser.add_argument("--no-paper", action="store_true", help="leave out the paper's network")
    args = parser.parse_args()
    ratios = [float(r) for r in args.ratios.split(",")]
    test = torch.load(args.weights, map_location="cpu", weights_only=False)["record"]["test"]
    paths = {mesh_name(p): p for p in list_meshes(args.data)}
    totals: dict[tuple[str, float], list[np.ndarray]] = {}
    for name in test:
        for key, value in evaluate(np.asarray(load_mesh(paths[name]).vertices, dtype=np.float64), ratios,
                                   None if args.no_paper else args.weights).items():
            totals.setdefault(key, []).append(value)
    print(f"TOSCA test split ({len(test)} meshes: {', '.join(test)}); means; CD on shapes as stored (mean convention)")
    print("| ratio | method | CD | CE | RE | SDM |")
    print("| ---: | --- | ---: | ---: | ---: | ---: |")
    for ratio in ratios:
        for method in sorted({method for method, _ in totals}, key=lambda m: (m != "fps", m)):
            cd, ce, re, sdm = np.mean(totals[(method, ratio)], axis=0)
            print(f"| {ratio} | {method} | {cd:.5g} | {ce:.5f} | {re:.5f} | {sdm:.4f} |", flush=True)


if __name__ == "__main__":
    main()
