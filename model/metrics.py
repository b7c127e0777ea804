"""Quality metrics of the paper (section 4) between a reference cloud and a simplified one, in numpy.

Chamfer distance uses the mean convention: mean over the reference of the squared distance to the
nearest simplified point plus the mean over the simplified cloud of the squared distance back (the
paper writes sums; means keep clouds of different sizes comparable). CE and RE follow the paper's
eq. (curvature error): the root mean square, over reference points, of the difference between the
reference's mean curvature (roughness for RE) and that of the nearest simplified point, each cloud's
features computed on the cloud itself (model/geometry.py, k = 16).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from model.geometry import PointFeatures, point_features


@dataclass(frozen=True)
class Quality:
    """The metrics of one simplification."""

    chamfer: float
    curvature_error: float
    roughness_error: float


def nearest(points: np.ndarray, queries: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Squared distance and index of each query's nearest point."""
    distance, index = cKDTree(points).query(queries, workers=-1)
    return np.square(distance), index


def chamfer_distance(reference: np.ndarray, simplified: np.ndarray) -> float:
    """Mean squared NN distance reference->simplified plus simplified->reference."""
    forward, _ = nearest(simplified, reference)
    backward, _ = nearest(reference, simplified)
    return float(forward.mean() + backward.mean())


def feature_error(reference_values: np.ndarray, simplified_values: np.ndarray, index: np.ndarray) -> float:
    """sqrt(mean_x (f1(x) - f2(NN(x)))^2): the paper's CE, or RE with roughness."""
    return float(np.sqrt(np.mean(np.square(reference_values - simplified_values[index]))))


def quality(reference: np.ndarray, simplified: np.ndarray, reference_features: PointFeatures | None = None) -> Quality:
    """CD, CE and RE of `simplified` against `reference` (pass reference features to reuse them)."""
    reference_features = reference_features or point_features(reference)
    simplified_features = point_features(simplified)
    _, index = nearest(simplified, reference)
    return Quality(chamfer_distance(reference, simplified),
                   feature_error(reference_features.mean_curvature, simplified_features.mean_curvature, index),
                   feature_error(reference_features.roughness, simplified_features.roughness, index))
