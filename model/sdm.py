"""SDM: the paper's structural distortion measure (section 4), after PC-MSDM (Meynet, Lavoue et al. 2019).

One direction, evaluated cloud E against the other cloud O. Around each point p of E, its neighbours j
give paired samples: a_j, E's mean curvature at j, and b_j, O's mean curvature at j's nearest point in
O (the paper's 1-NN correspondence; PC-MSDM projects onto a fitted quadric instead). Gaussian-weighted
means mu, standard deviations s and covariance s_ab of the samples give
    L = |mu_a - mu_b| / (max(mu_a, mu_b) + c)       C = |s_a - s_b| / (max(s_a, s_b) + c)
    S = min(1, |s_a s_b - s_ab| / (s_a s_b + c))    LD = (L + C + S / 2) / 2.5
with PC-MSDM's weights (1, 1, 0.5) and its clamp of S. The paper's text divides C by the max of the
means and squares s_ab in S; PC-MSDM's code, which the paper cites, does neither, and we follow it.
The score of a direction is Minkowski pooling (mean LD^3)^(1/3) (PC-MSDM's exponent 3); the SDM is the
mean of both directions. Identical clouds give exactly 0 up to round-off.

Neighbourhood: the k = 16 nearest neighbours of p in E (the kNN of model/geometry.py, reused) weighted by
exp(-d^2 / h_p), h_p the squared distance to the 8th neighbour (geometry.bandwidth): a radius tied to the
local spacing. PC-MSDM's one radius, a fraction of the bounding box, is metres on a city scan: thousands
of points in dense areas and none far from the scanner.
"""
from __future__ import annotations

import numpy as np

from model.geometry import CHUNK_POINTS, PointFeatures, bandwidth

WEIGHTS = (1.0, 1.0, 0.5)  # L, C, S as in PC-MSDM
POOLING_EXPONENT = 3.0
STABILISER = 1e-3  # c, in mean-curvature units ([0, 1/3]); keeps flat-vs-flat round-off from scoring


def structural_distortion(a: PointFeatures, b: PointFeatures, a_to_b: np.ndarray, b_to_a: np.ndarray,
                          a_scored: np.ndarray | None = None, b_scored: np.ndarray | None = None) -> float:
    """SDM between two clouds from their features and each point's nearest-point index in the other cloud,
    pooled over the scored point indices of each (all when None)."""
    return (directed_sdm(a, b.mean_curvature[a_to_b], a_scored)
            + directed_sdm(b, a.mean_curvature[b_to_a], b_scored)) / 2


def directed_sdm(features: PointFeatures, other_at_nearest: np.ndarray, scored: np.ndarray | None = None) -> float:
    """Pooled local distortion of one cloud (over its `scored` point indices), given the other cloud's mean
    curvature at each point's nearest point."""
    nbrs, own = features.nbrs, features.mean_curvature.astype(np.float64)
    other_at_nearest = other_at_nearest.astype(np.float64)
    h = bandwidth(nbrs)
    scored = np.arange(len(own)) if scored is None else scored
    pooled = 0.0
    for start in range(0, len(scored), CHUNK_POINTS):
        rows = scored[start:start + CHUNK_POINTS]
        index = nbrs.indices[rows]
        weights = np.exp(-nbrs.sq_dist[rows].astype(np.float64) / h[rows, None])
        weights /= weights.sum(axis=1, keepdims=True)
        distortion = local_distortion(own[index], other_at_nearest[index], weights)
        pooled += float(np.sum(distortion**POOLING_EXPONENT))
    return (pooled / max(len(scored), 1)) ** (1 / POOLING_EXPONENT)


def local_distortion(a: np.ndarray, b: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """LD of each row of paired samples (m, k) under normalised weights (m, k)."""
    mu_a, mu_b = np.sum(weights * a, axis=1), np.sum(weights * b, axis=1)
    da, db = a - mu_a[:, None], b - mu_b[:, None]
    s_a, s_b = np.sqrt(np.sum(weights * da * da, axis=1)), np.sqrt(np.sum(weights * db * db, axis=1))
    s_ab = np.sum(weights * da * db, axis=1)
    luminance = np.abs(mu_a - mu_b) / (np.maximum(mu_a, mu_b) + STABILISER)
    contrast = np.abs(s_a - s_b) / (np.maximum(s_a, s_b) + STABILISER)
    structure = np.minimum(1.0, np.abs(s_a * s_b - s_ab) / (s_a * s_b + STABILISER))
    alpha, beta, gamma = WEIGHTS
    return (alpha * luminance + beta * contrast + gamma * structure) / (alpha + beta + gamma)
