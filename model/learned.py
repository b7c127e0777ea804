"""The paper's trained network behind the simplifier interface (`--method paper`, `paper-refined`)."""
from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from model.baselines import farthest_core_picks
from model.learning import PAPER_WEIGHTS
from model.learning.checkpoint import load_trained
from model.learning.network import LearnedSimplifier, knn_graph, latent_fps, normalise, row_blocks
from model.selection import Selection, Tile

REDUCED_DIMS = 8  # fpsample's bucket FPS handles at most 8 dimensions
PCA_SAMPLE = 4096  # about this many feature rows (an even stride) fix the principal axes


@lru_cache(maxsize=2)
def load_model(path: Path = PAPER_WEIGHTS) -> LearnedSimplifier:
    """The network with trained weights, in inference mode, BatchNorm (running statistics) folded in."""
    model = load_trained(LearnedSimplifier(), path, "pipeline train")
    model.projector.fold_batchnorm()
    return model


def reduced_latent_order(feature_rows: Callable[[slice | torch.Tensor], torch.Tensor], count: int,
                         core: np.ndarray, budget: int, seed: int) -> np.ndarray:
    """Core picks of FPS in the top-8 principal components of the 64-d features, by fpsample's bucket FPS.

    Exact latent FPS costs O(n*m*64) in a Python loop (1.6 s for a 35k-point tile at 0.1); this ran
    0.08 s on the same tile, keeping 93 % of the feature variance. The paper's FPS is over all 64
    dimensions: `exact=True` in learned_simplify keeps that. `feature_rows(rows)` gives the features of
    some rows: the axes come from an even stride of them, and each block is projected as it comes,
    so the (n, 64) features need not exist at once.
    """
    sampled = feature_rows(torch.arange(0, count, max(1, count // PCA_SAMPLE)))
    centre = sampled.mean(dim=0)
    top = torch.linalg.svd(sampled - centre, full_matrices=False).Vh[:REDUCED_DIMS].T  # fewer for a tiny tile
    reduced = torch.empty(count, top.shape[1])
    for rows in row_blocks(count):
        reduced[rows] = (feature_rows(rows) - centre) @ top
    return farthest_core_picks(Tile(reduced.numpy(), core, np.zeros(top.shape[1]), seed), budget).indices


def exact_latent_order(features: torch.Tensor, tile: Tile, budget: int) -> np.ndarray:
    """The paper's selector: FPS over all 64 feature dimensions from a seeded core point, core picks kept."""
    core = torch.from_numpy(tile.core)
    core_index = np.flatnonzero(tile.core)
    start = int(core_index[np.random.default_rng(tile.seed).integers(len(core_index))])
    order = latent_fps(features, budget, start, keep=core)
    return order[core[order]][:budget].numpy()


@torch.no_grad()
def learned_simplify(tile: Tile, budget: int, weights: Path = PAPER_WEIGHTS, exact: bool = False,
                     graph: np.ndarray | None = None, refine: bool = False) -> Selection:
    """Latent FPS over core+halo until `budget` core picks, then (if `refine`) each pick moved by the
    attention refinement over its neighbourhood; without it the picks keep their measured positions.

    The input is normalised exactly as in training (centre, unit ball); refined positions are mapped back.
    `graph` ((n, k) rows, each point first; mesh mode passes mesh adjacency) replaces the kNN graph in the
    GNN layer only: refinement always attends over each pick's nearest input points, as in the paper.
    """
    budget = min(budget, tile.core_count)
    if budget == 0:
        return Selection.of(tile, np.empty(0, dtype=np.int64))
    model = load_model(weights)
    xyz64 = torch.from_numpy(np.ascontiguousarray(tile.xyz, dtype=np.float64))
    normalised, centre, scale = normalise(xyz64)
    xyz = normalised.float()
    neighbours = knn_graph(xyz.numpy())
    adjacency = neighbours if graph is None else torch.from_numpy(np.ascontiguousarray(graph, dtype=np.int64))
    if exact or refine:
        features = model.projector.infer(xyz, adjacency)
        feature_rows = lambda rows: features[rows]  # noqa: E731
    else:  # the default: the 64-d features are only needed projected to 8, block by block
        pointwise = model.projector.pointwise_features(xyz)
        feature_rows = lambda rows: model.projector.aggregate(pointwise, adjacency[rows], rows)  # noqa: E731
    if exact:
        picks = exact_latent_order(features, tile, budget)
    else:
        picks = reduced_latent_order(feature_rows, len(xyz), tile.core, budget, tile.seed)
    if not refine:
        return Selection.of(tile, picks)
    refined = model.refiner(xyz, features, torch.from_numpy(picks), neighbours).double() * scale + centre
    return Selection(picks.astype(np.int64), refined.numpy())
