"""Quality metrics of the paper (section 4) between a reference cloud and a simplified one, in numpy.

Conventions (lower is better for every metric; identical clouds score 0 on all):
- Chamfer distance (CD): mean over the reference of the squared distance to the nearest simplified
  point plus the mean over the simplified cloud of the squared distance back (the paper writes sums;
  means keep clouds of different sizes comparable). A shift by d smaller than the spacing gives 2 d^2.
- Hausdorff distance: the larger of the two directed maxima of the (plain, not squared) Euclidean
  distance to the nearest point of the other cloud.
- Normal consistency (NC): the paper's bi-directional 1 - cos between a point's normal and its nearest
  neighbour's in the other cloud, with the two directions averaged (the paper sums them: its values are
  twice ours). PCA normals have no sign, so by default each term is 1 - |cos| (0 same plane, 1
  perpendicular); with oriented normals supplied, 1 - cos (2 where flipped).
- CE and RE follow the paper's eq. (curvature error): the root mean square, over reference points, of
  the difference between the reference's mean curvature (roughness for RE) and that of the nearest
  simplified point.
- SDM: model/sdm.py.
Each cloud's features come from one kNN query on the cloud itself (model/geometry.py, k = 16), and each
direction's nearest neighbours are queried once and shared by all metrics. Queries run in chunks.
A sample of a big cloud can be scored on some points only: the others (a margin around the sample)
serve as neighbours and nearest points, so points at the sample's edge are scored as in the whole cloud.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from model.geometry import CHUNK_POINTS, PointFeatures, PointTree, point_features
from model.sdm import structural_distortion


@dataclass(frozen=True)
class Quality:
    """The metrics of one simplification (see the module docstring for the conventions)."""

    chamfer: float
    curvature_error: float
    roughness_error: float
    hausdorff: float
    normal_consistency: float
    sdm: float


@dataclass(frozen=True)
class Match:
    """Each query point's nearest point in the other cloud: squared distance and index."""

    sq_dist: np.ndarray
    index: np.ndarray

    def of(self, rows: np.ndarray) -> "Match":
        """The matches of some query points only."""
        return Match(self.sq_dist[rows], self.index[rows])


def nearest(points: np.ndarray, queries: np.ndarray) -> Match:
    """The nearest of `points` to each query, queried in chunks so millions of queries fit in memory."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    queries = np.ascontiguousarray(queries, dtype=np.float64)
    tree = PointTree.of(points, 1)
    sq_dist = np.empty(len(queries))
    index = np.empty(len(queries), dtype=np.int64)
    for start in range(0, len(queries), CHUNK_POINTS):
        stop = start + CHUNK_POINTS
        sq_dist[start:stop], index[start:stop] = tree.query(queries[start:stop], 1)
    return Match(sq_dist, index)


def chamfer_distance(reference: np.ndarray, simplified: np.ndarray) -> float:
    """Mean squared NN distance reference->simplified plus simplified->reference."""
    return _chamfer(nearest(simplified, reference), nearest(reference, simplified))


def hausdorff_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Symmetric Hausdorff distance (Euclidean, not squared): the larger directed maximum."""
    return _hausdorff(nearest(b, a), nearest(a, b))


def normal_consistency(a: np.ndarray, b: np.ndarray, normals_a: np.ndarray | None = None,
                       normals_b: np.ndarray | None = None, oriented: bool = False) -> float:
    """Mean over both directions of 1 - |cos| (1 - cos if `oriented`) between NN normals; PCA normals if not given."""
    normals_a = point_features(a).normals if normals_a is None else normals_a
    normals_b = point_features(b).normals if normals_b is None else normals_b
    return (_directed_nc(normals_a, normals_b, nearest(b, a), oriented)
            + _directed_nc(normals_b, normals_a, nearest(a, b), oriented)) / 2


def feature_error(reference_values: np.ndarray, simplified_values: np.ndarray, index: np.ndarray) -> float:
    """sqrt(mean_x (f1(x) - f2(NN(x)))^2): the paper's CE, or RE with roughness."""
    return float(np.sqrt(np.mean(np.square(reference_values - simplified_values[index]))))


def quality(reference: np.ndarray, simplified: np.ndarray, reference_features: PointFeatures | None = None,
            reference_scored: np.ndarray | None = None, simplified_scored: np.ndarray | None = None) -> Quality:
    """Every metric of `simplified` against `reference` (pass reference features to reuse them), over the
    points each `*_scored` mask selects (all when None); the other points are neighbours and matches only."""
    ref = reference_features or point_features(reference)
    simp = point_features(simplified)
    forward, backward = nearest(simplified, reference), nearest(reference, simplified)
    a = np.flatnonzero(reference_scored) if reference_scored is not None else np.arange(len(reference))
    b = np.flatnonzero(simplified_scored) if simplified_scored is not None else np.arange(len(simplified))
    fa, fb = forward.of(a), backward.of(b)
    return Quality(chamfer=_chamfer(fa, fb),
                   curvature_error=feature_error(ref.mean_curvature[a], simp.mean_curvature, fa.index),
                   roughness_error=feature_error(ref.roughness[a], simp.roughness, fa.index),
                   hausdorff=_hausdorff(fa, fb),
                   normal_consistency=(_directed_nc(ref.normals[a], simp.normals, fa)
                                       + _directed_nc(simp.normals[b], ref.normals, fb)) / 2,
                   sdm=structural_distortion(ref, simp, forward.index, backward.index, a, b))


def _chamfer(forward: Match, backward: Match) -> float:
    return float(forward.sq_dist.mean() + backward.sq_dist.mean())


def _hausdorff(forward: Match, backward: Match) -> float:
    return float(np.sqrt(max(forward.sq_dist.max(), backward.sq_dist.max())))


def _directed_nc(normals: np.ndarray, other: np.ndarray, match: Match, oriented: bool = False) -> float:
    """Mean of 1 - |cos| (1 - cos if oriented) between each query point's normal and its match's in `other`."""
    total = 0.0
    for start in range(0, len(normals), CHUNK_POINTS):
        stop = start + CHUNK_POINTS
        cos = np.einsum("ij,ij->i", _unit(normals[start:stop]), _unit(other[match.index[start:stop]]))
        cos = np.clip(cos, -1, 1)  # round-off can pass 1, and NC of twins must be 0, not -1e-17
        total += float(np.sum(1 - (cos if oriented else np.abs(cos))))
    return total / len(normals)


def _unit(vectors: np.ndarray) -> np.ndarray:
    """Vectors scaled to unit length in float64 (zero vectors stay zero)."""
    vectors = np.asarray(vectors, dtype=np.float64)
    length = np.linalg.norm(vectors, axis=1, keepdims=True)
    return np.divide(vectors, length, out=np.zeros_like(vectors), where=length > 0)
