"""The paper's training losses in torch: adaptive Chamfer distance and curvature error (CE).

Conventions chosen here (the paper leaves them open; recorded in the model card):
- Chamfer terms are means over points, not sums, so the loss does not grow with cloud size;
- curvature weights w = sigmoid(tau * K / max K) with tau = 10: the footnote's "divided by a temperature"
  would give sigmoid(K / (10 max K)), within 0.5..0.525 for every point, i.e. no adaptivity at all;
  multiplying spans 0.5 (flat) to ~1 (the most curved point), which is what "amplify" asks for;
- mean curvature of both clouds from the same differentiable estimator (`mean_curvature` below), the
  torch twin of model/geometry.py: k = 16 neighbours including the point, covariance about the point.
"""
from __future__ import annotations

import torch

TAU = 10.0
CURVATURE_NEIGHBOURS = 16


def curvature_weights(mean_curvature: torch.Tensor, tau: float = TAU) -> torch.Tensor:
    """Per-point weights of the adaptive Chamfer distance's first term."""
    return torch.sigmoid(tau * mean_curvature / mean_curvature.max().clamp_min(1e-12))


def adaptive_chamfer(source: torch.Tensor, simplified: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Weighted mean of source->simplified squared NN distances plus the plain simplified->source mean."""
    squared = torch.cdist(source, simplified).square()
    forward = (weights * squared.min(dim=1).values).sum() / weights.sum()
    return forward + squared.min(dim=0).values.mean()


def knn_indices(points: torch.Tensor, k: int) -> torch.Tensor:
    """(n, k) indices of each point's k nearest points, itself first (no gradient through the choice)."""
    with torch.no_grad():
        return torch.cdist(points, points).topk(min(k, points.shape[0]), largest=False).indices


def mean_curvature(points: torch.Tensor, k: int = CURVATURE_NEIGHBOURS) -> torch.Tensor:
    """Differentiable K-bar, as model/geometry.py computes it: kappa = l0/(l0+l1+l2) of the covariance about
    each point over its k-NN (itself first), then a Gaussian-weighted mean over the same neighbours with
    h = squared distance to the (k/2)-th neighbour (geometry.bandwidth)."""
    neighbours = knn_indices(points, k)
    offsets = points[neighbours] - points[:, None, :]                      # (n, k, 3)
    covariance = offsets.transpose(1, 2) @ offsets                          # (n, 3, 3)
    eigenvalues = torch.linalg.eigvalsh(covariance + 1e-12 * torch.eye(3))  # ascending
    kappa = eigenvalues[:, 0] / eigenvalues.sum(dim=1).clamp_min(1e-12)
    squared = offsets.square().sum(-1)                                      # (n, k)
    h = squared[:, neighbours.shape[1] // 2 : neighbours.shape[1] // 2 + 1].detach()
    weights = torch.exp(-squared / torch.where(h > 0, h, torch.inf))
    return (weights * kappa[neighbours]).sum(1) / weights.sum(1)


def curvature_error(source: torch.Tensor, source_curvature: torch.Tensor, simplified: torch.Tensor,
                    simplified_curvature: torch.Tensor) -> torch.Tensor:
    """CE = sqrt(mean over source points of (K1(x) - K2(NN(x, simplified)))^2)."""
    with torch.no_grad():
        nearest = torch.cdist(source, simplified).argmin(dim=1)
    return (source_curvature - simplified_curvature[nearest]).square().mean().sqrt()


def total_loss(source: torch.Tensor, source_curvature: torch.Tensor, simplified: torch.Tensor,
               weight: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Adaptive CD + weight * CE, and the two terms (for logging)."""
    chamfer = adaptive_chamfer(source, simplified, curvature_weights(source_curvature))
    error = curvature_error(source, source_curvature, simplified, mean_curvature(simplified))
    return chamfer + weight * error, chamfer, error
