"""The learned curvature-loss predictor behind `--method learned` (trained on TOSCA: model/learning/detail_training.py).

Why: CE, the paper's curvature error, adds up per point how far thinning moves the mean curvature;
model/stratified.curvature_loss measures that for one even thinning of a tile, a noisy sample (another
thinning's loss correlates with it only partly). A small network predicts the expected loss from that
sample and descriptors of the cloud (eigenvalue shares, curvature statistics over the neighbourhood,
spacing ratios, the ratio kept), invariant to translation and scale, and but for the measured sample to
rotation, so absolute position in a tile, the unit of the scan and the tile's extent cannot leak in, as
they do into the paper's latent features. Trained on TOSCA shapes sampled the way a scanner samples them.
The prediction sets the stratified fill's keep weights 1 + loss / mean loss (model.stratified.fill_weights).

A tile is described at the output's scale: thinned evenly to DESCRIBED_PER_PICK points per pick (see
described_tile), each point then told the prediction of the nearest described one. Against describing
every point, at 0.1 and 0.05 on the eight scans of bench/quality.py: CE 1-10 % lower on 15 of 16 (4 %
higher on the extra-bytes file at 0.05), SDM 1-4 % lower on all, Chamfer within 2 % but on the
extra-bytes file (6-9 % higher); at 0.2 it changes little, describing 80 % of the points. The survey's work
falls with the ratio (bcts_1+2 at 0.1: 9.3 -> 5.9 s on one thread). Small steps such as the simulated kerb
keep less of their extra share at 0.05 (1.08 -> 0.71 of the ratio's share; FPS 0.25).
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from model.geometry import FRAME_POINTS, PointTree, local_features, nearest_member, roughness
from model.learning import DETAIL_WEIGHTS
from model.selection import FillLoss, Tile
from model.rules import morton_order
from model.stratified import curvature_loss, systematic_picks

SOFTPLUS_LINEAR = 20.0  # torch's softplus returns its input above this
DESCRIPTORS = 12
HIDDEN = 32
NEIGHBOURS = 16
DESCRIBED_PER_PICK = 4  # the loss is described on an even thinning to this many points per pick (a ratio of 1/4,
                        # inside the [0.05, 0.3] the predictor was trained on): it is the loss at the output's scale
SURVEY_BLOCK = 32_768  # core rows described at a time: a tile's (rows, 16) neighbour tables never exist whole


def descriptors(tile: Tile, budget: int, phase: float = 0.5) -> np.ndarray:
    """(c, 12) float32 descriptors of a tile's c core points, in tile order (see described)."""
    return described(tile, budget, phase)[0]


def described(tile: Tile, budget: int, phase: float = 0.5) -> tuple[np.ndarray, float]:
    """(c, 12) float32 descriptors of the c core points of a tile to be thinned to `budget` of them:
    curvature kappa, the middle eigenvalue share, mean curvature, roughness, mean / std / max of kappa and
    std of mean curvature over the 16 neighbours, the 1st and 8th neighbour distances over the 16th,
    log(ratio), and the curvature loss of the even thinning at `phase` over its core mean
    (model.stratified.curvature_loss: a noisy sample of what is predicted). Unchanged by translation and
    scale; by rotation too, but for the measured loss (the Morton curve, so the thinning measured, turns
    with the axes). Also the measured loss's core mean (K units): the scale that the relative prediction
    is read against. The halo serves as neighbours only (model.geometry.local_features), so neither its
    width nor its own losses change what the core is told. The core is described SURVEY_BLOCK points at a
    time, along the Z-order curve (a 200k-point tile's survey peaked at 73 MiB traced whole): the values
    are those of one pass."""
    core = np.flatnonzero(tile.core)
    xyz = np.ascontiguousarray(tile.xyz, dtype=np.float64)
    tree = PointTree.of(xyz, NEIGHBOURS)
    features = np.empty((len(core), DESCRIPTORS), dtype=np.float32)
    kbar = np.empty(len(core), dtype=np.float32)
    for block in np.array_split(tile.core_order, -(-len(core) // SURVEY_BLOCK)) if len(core) else []:
        features[block], kbar[block] = described_rows(xyz, core[block], tree)
    measured = curvature_loss(tile, budget, phase, here=kbar)
    features[:, 10] = np.log(budget / tile.core_count)
    features[:, 11] = relative(measured)
    return features, float(measured.mean()) if len(measured) else 0.0


def described_rows(xyz: np.ndarray, rows: np.ndarray, tree: PointTree) -> tuple[np.ndarray, np.ndarray]:
    """(m, 12) float32 descriptors of xyz[rows] but for the last two (set by described), and their mean
    curvature (m,) float32; `tree` holds xyz (n, 3) float64 (PointTree). Rows in curve order, so the rings of
    neighbours beyond them (queried again by the next block) are a thin border."""
    local = local_features(xyz, rows, NEIGHBOURS, np.arange(len(rows)), tree)
    nbrs = local.nbrs
    kappa, kbar = local.kappa[rows], local.mean_curvature[rows]
    total = local.eigenvalues.sum(axis=1)
    middle = np.divide(local.eigenvalues[:, 1], total, out=np.zeros(len(total)), where=total > 0)
    nearest, middle_one, farthest = np.sqrt(nbrs.sq_dist[:, [min(1, nbrs.k - 1), nbrs.k // 2, -1]].astype(np.float64)).T
    far = np.where(farthest > 0, farthest, 1.0)
    features = np.zeros((len(rows), DESCRIPTORS), dtype=np.float32)
    features[:, :4] = np.column_stack([kappa, middle, kbar, roughness(kappa, kbar)])
    features[:, 4:8] = spread_over_neighbours(local.kappa, local.mean_curvature, nbrs.indices)
    features[:, 8:10] = np.column_stack([nearest / far, middle_one / far])
    return features, kbar


def spread_over_neighbours(kappa: np.ndarray, kbar: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """(m, 4) float32: mean, std and max of kappa and std of mean curvature kbar (both (n,) float32) over
    each row's neighbours (indices (m, k)); a batch of rows at a time, so the (m, k) gathers never exist
    whole (a 200k-point tile's are 13 MB each)."""
    spread = np.empty((len(indices), 4), dtype=np.float32)
    for start in range(0, len(indices), FRAME_POINTS):
        rows = slice(start, start + FRAME_POINTS)
        around = kappa[indices[rows]]
        spread[rows] = np.column_stack([around.mean(axis=1), around.std(axis=1), around.max(axis=1),
                                        kbar[indices[rows]].std(axis=1)])
    return spread


def described_tile(tile: Tile, budget: int) -> tuple[Tile, np.ndarray]:
    """What the loss is described on: the tile thinned evenly to DESCRIBED_PER_PICK points per pick of
    `budget` (core along the tile's curve, halo alike along its own, so the core's neighbours there are as
    dense), or the tile itself where that keeps every point; and for each core point of `tile` (c,) the
    position, among the thinned tile's core points, of the nearest of them (its own, if kept)."""
    count = min(tile.core_count, DESCRIBED_PER_PICK * budget)
    if count == tile.core_count:
        return tile, np.arange(count)
    halo = np.flatnonzero(~tile.core)
    halo_count = round(len(halo) * count / tile.core_count)
    halo_curve = halo[morton_order(tile.xyz[halo])] if len(halo) else halo
    kept = np.sort(np.concatenate([systematic_picks(tile.curve, count, 0.5), systematic_picks(halo_curve, halo_count, 0.5)]))
    seen = Tile(tile.xyz[kept], tile.core[kept], tile.centre, tile.seed)
    return seen, nearest_member(tile.xyz, kept[seen.core], np.flatnonzero(tile.core))


def relative(loss: np.ndarray, cap: float = 20.0) -> np.ndarray:
    """A loss over its mean, capped (a few isolated points reach hundreds)."""
    return np.minimum(loss / max(float(loss.mean()), 1e-12), cap) if len(loss) else loss


@dataclass(frozen=True)
class DetailWeights:
    """The trained predictor as numpy arrays (what model/learning/detail_net.py's network holds): descriptor shift and
    spread (12,), and three dense layers (out, in) with biases, ReLU between, softplus last."""

    shift: np.ndarray
    spread: np.ndarray
    layers: tuple[tuple[np.ndarray, np.ndarray], ...]

    def predict(self, features: np.ndarray) -> np.ndarray:
        """(n,) float32 predicted relative loss >= 0 of (n, 12) float32 descriptors, as the torch network
        computes it (float32 throughout; softplus as torch's, linear above 20), a batch of rows at a time:
        a 200k-point tile's hidden layers are 26 MB each."""
        predicted = np.empty(len(features), dtype=np.float32)
        for start in range(0, len(features), FRAME_POINTS):
            rows = slice(start, start + FRAME_POINTS)
            x = (features[rows] - self.shift) / self.spread
            for number, (weight, bias) in enumerate(self.layers):
                x = x @ weight.T + bias
                if number < len(self.layers) - 1:
                    x = np.maximum(x, 0)
            x = x[:, 0]
            predicted[rows] = np.where(x > SOFTPLUS_LINEAR, x, np.log1p(np.exp(np.minimum(x, SOFTPLUS_LINEAR))))
        return predicted


@lru_cache(maxsize=2)
def load_detail_weights(path: Path = DETAIL_WEIGHTS) -> DetailWeights:
    """The shipped predictor (an .npz exported by `pipeline train-detail` beside its .pt): no torch needed,
    so workers of the default method never import it (1.6 s and about 180 MB each)."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no trained weights (train them with `pipeline train-detail`)")
    with np.load(path, allow_pickle=False) as saved:
        count = sum(1 for name in saved.files if name.startswith("weight_"))
        layers = tuple((saved[f"weight_{i}"], saved[f"bias_{i}"]) for i in range(count))
        return DetailWeights(saved["shift"], saved["spread"], layers)


def predicted_loss(tile: Tile, budget: int, path: Path = DETAIL_WEIGHTS) -> np.ndarray:
    """(n,) expected curvature loss of each tile point, over the mean, for an even thinning to `budget`."""
    return predicted_fill_loss(tile, budget, path).relative


def predicted_fill_loss(tile: Tile, budget: int, path: Path = DETAIL_WEIGHTS) -> FillLoss:
    """The expected loss of each tile point (n,) over its core mean, 0 in the halo, and that mean in K
    units (the measured mean times the prediction's core mean, since the network predicts relative to
    the measured mean)."""
    seen, core_of = described_tile(tile, budget)
    features, measured_level = described(seen, budget)
    predicted = np.zeros(len(tile.xyz))
    predicted[tile.core] = load_detail_weights(path).predict(features)[core_of]
    core_mean = float(predicted[tile.core].mean()) if tile.core.any() else 0.0
    if core_mean <= 0:
        return FillLoss(np.zeros_like(predicted), 0.0)
    return FillLoss(predicted / core_mean, core_mean * measured_level)
