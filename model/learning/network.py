"""The paper's network: projector (point-wise MLP + one GNN layer), latent FPS selector, attention refinement.

Choices the paper leaves open, made here and recorded in the model card:
- input normalisation: centre on the mean, scale so the farthest point is at distance 1 (training and inference);
- GNN neighbourhood: the k=16 nearest neighbours (self excluded) by a mean through a sparse CSR matrix, so
  200k-point tiles aggregate without materialising (n, k, 64) tensors;
- refinement: each centre attends over its 16-NN row (itself and its 15 nearest input points);
  attention width d = 16; phi: 67 -> 64 -> 3 (ReLU), gamma: 3 -> 16 -> 3 (ReLU);
- FPS start: a seeded random point (the paper saw no influence of the start).
"""
from __future__ import annotations

import math
import warnings

import numpy as np
import torch
from torch import nn
from torch.nn.utils.fusion import fuse_linear_bn_eval

from model.geometry import knn

FEATURES = 64
GRAPH_NEIGHBOURS = 16
ATTENTION_DIM = 16
INFERENCE_ROWS = 16_384  # rows per block of Projector.infer


def normalise(xyz: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Centre on the mean and scale into the unit ball; returns (normalised, centre, scale)."""
    centre = xyz.mean(dim=0)
    scale = (xyz - centre).norm(dim=1).max().clamp_min(1e-12)
    return (xyz - centre) / scale, centre, scale


def knn_graph(points: np.ndarray) -> torch.Tensor:
    """(n, k) indices of each point's GRAPH_NEIGHBOURS nearest points, itself first even among duplicates."""
    return torch.from_numpy(knn(points, GRAPH_NEIGHBOURS).indices)


def mean_operator(neighbours: torch.Tensor, count: int) -> torch.Tensor:
    """Sparse CSR (rows, count) matrix whose product with the (count, d) features averages each row's
    neighbours (self excluded): rows are the points of `neighbours`, all of them or a block.

    Every row has the same k-1 entries, so the CSR arrays are written directly: no sort or coalesce
    (60x faster to build than COO on a 38k-point tile, and its product 2.4x faster). Indices are int32
    where they fit: half the memory, the same product time.
    """
    width = neighbours.shape[1] - 1
    index_type = torch.int32 if count * width < 2**31 else torch.int64
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")
        return torch.sparse_csr_tensor(torch.arange(count + 1, dtype=index_type) * width,
                                       neighbours[:, 1:].to(index_type).reshape(-1),
                                       torch.full((count * width,), 1.0 / max(width, 1)),  # a lone point: no entries
                                       (len(neighbours), count), check_invariants=False)


class Projector(nn.Module):
    """Three point-wise Linear+BatchNorm+ReLU layers of 64, then f' = ReLU(W_c f + mean_j W_n f_j)."""

    def __init__(self) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        width = 3
        for _ in range(3):
            layers += [nn.Linear(width, FEATURES), nn.BatchNorm1d(FEATURES), nn.ReLU()]
            width = FEATURES
        self.pointwise = nn.Sequential(*layers)
        self.centre = nn.Linear(FEATURES, FEATURES)
        self.neighbour = nn.Linear(FEATURES, FEATURES, bias=False)

    def fold_batchnorm(self) -> None:
        """Fold each eval-mode BatchNorm into its Linear (same outputs, fewer passes): for inference only."""
        layers = list(self.pointwise)
        fused: list[nn.Module] = []
        for linear, norm, activation in zip(layers[0::3], layers[1::3], layers[2::3]):
            fused += [fuse_linear_bn_eval(linear, norm), activation]
        self.pointwise = nn.Sequential(*fused)

    def forward(self, xyz: torch.Tensor, mean: torch.Tensor) -> torch.Tensor:
        features = self.pointwise(xyz)
        # mean_j W_n f_j = W_n (mean_j f_j): aggregate first, one sparse product
        return torch.relu(self.centre(features) + self.neighbour(mean @ features))

    @torch.no_grad()
    def infer(self, xyz: torch.Tensor, neighbours: torch.Tensor) -> torch.Tensor:
        """forward's result over the (n, k) graph rows, computed in row blocks so only two (n, 64)
        tensors are alive at once.

        forward keeps about six, and a whole-tile sparse product allocates twice its output: a
        250k-point tile's transient went from about 300 MB to 210 MB (140 MB where only an 8-d
        projection of the output is needed: model.learned.reduced_latent_order).
        """
        features = self.pointwise_features(xyz)
        result = torch.empty_like(features)
        for rows in row_blocks(len(xyz)):
            result[rows] = self.aggregate(features, neighbours[rows], rows)
        return result

    @torch.no_grad()
    def pointwise_features(self, xyz: torch.Tensor) -> torch.Tensor:
        """The (n, 64) output of the point-wise layers, computed in row blocks."""
        features = torch.empty(len(xyz), FEATURES)
        for rows in row_blocks(len(xyz)):
            features[rows] = self.pointwise(xyz[rows])
        return features

    @torch.no_grad()
    def aggregate(self, features: torch.Tensor, neighbours: torch.Tensor, rows: slice | torch.Tensor) -> torch.Tensor:
        """The GNN layer's output for `rows` (a block or any index), given their graph rows `neighbours`."""
        means = mean_operator(neighbours, len(features)) @ features
        return torch.relu(self.centre(features[rows]) + self.neighbour(means))


def row_blocks(count: int) -> list[slice]:
    """Consecutive slices of INFERENCE_ROWS rows covering `count` rows."""
    return [slice(start, start + INFERENCE_ROWS) for start in range(0, count, INFERENCE_ROWS)]


@torch.no_grad()
def latent_fps(features: torch.Tensor, count: int, start: int, keep: torch.Tensor | None = None) -> torch.Tensor:
    """Farthest point sampling in feature space, in FPS order (a prefix is a coarser pick).

    Runs until `count` picks satisfy `keep` (all picks count when keep is None) and returns every pick
    made, so a tile can sample over core+halo and keep its core picks.
    """
    features = features.detach().contiguous()
    norms = (features * features).sum(dim=1)
    nearest = torch.full((features.shape[0],), math.inf, dtype=features.dtype)
    limit = features.shape[0] if keep is not None else count
    order = torch.empty(limit, dtype=torch.long)
    current, kept, step = start, 0, 0
    while kept < count and step < limit:
        order[step] = current
        kept += 1 if keep is None or bool(keep[current]) else 0
        step += 1
        distance = norms + norms[current] - 2 * torch.mv(features, features[current])
        nearest = torch.minimum(nearest, distance)
        nearest[current] = -math.inf  # never pick a chosen point again, even among exact duplicates
        current = int(torch.argmax(nearest))
    return order[:step]


class Refiner(nn.Module):
    """p' = p + gamma(mean_j a_ij phi([f_j || p_j - p])), a = softmax over j of theta_q(p_j).theta_k(p)/sqrt(d)."""

    def __init__(self) -> None:
        super().__init__()
        self.query = nn.Linear(3, ATTENTION_DIM)
        self.key = nn.Linear(3, ATTENTION_DIM)
        self.phi = nn.Sequential(nn.Linear(FEATURES + 3, FEATURES), nn.ReLU(), nn.Linear(FEATURES, 3))
        self.gamma = nn.Sequential(nn.Linear(3, 16), nn.ReLU(), nn.Linear(16, 3))

    def forward(self, xyz: torch.Tensor, features: torch.Tensor, centres: torch.Tensor,
                neighbours: torch.Tensor) -> torch.Tensor:
        group = neighbours[centres]                                  # (m, k): each centre's nearest input points
        centre_xyz = xyz[centres]
        offsets = xyz[group] - centre_xyz[:, None, :]
        logits = (self.query(xyz[group]) * self.key(centre_xyz)[:, None, :]).sum(-1) / math.sqrt(ATTENTION_DIM)
        attention = torch.softmax(logits, dim=1)
        messages = self.phi(torch.cat([features[group], offsets], dim=-1))
        return centre_xyz + self.gamma((attention[..., None] * messages).mean(dim=1))


class LearnedSimplifier(nn.Module):
    """Projector -> latent FPS -> refinement, on normalised xyz with a precomputed kNN graph (self first)."""

    def __init__(self) -> None:
        super().__init__()
        self.projector = Projector()
        self.refiner = Refiner()

    def forward(self, xyz: torch.Tensor, neighbours: torch.Tensor, count: int,
                start: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Indices of `count` centres in FPS order and their refined positions."""
        features = self.projector(xyz, mean_operator(neighbours, xyz.shape[0]))
        centres = latent_fps(features, count, start)
        return centres, self.refiner(xyz, features, centres, neighbours)
