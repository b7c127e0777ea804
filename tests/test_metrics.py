"""Analytic cases for the paper's metrics: twins score 0, known shifts, subsets and normals give known values."""
import numpy as np
import pytest
from scipy.spatial.distance import cdist

from model.metrics import chamfer_distance, hausdorff_distance, normal_consistency, quality


def sphere(n: int, seed: int = 0) -> np.ndarray:
    v = np.random.default_rng(seed).normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def test_identical_clouds_score_zero():
    x = sphere(2_000)
    q = quality(x, x)
    assert q.chamfer == 0 and q.curvature_error == 0 and q.roughness_error == 0
    assert q.hausdorff == 0
    assert q.normal_consistency == pytest.approx(0, abs=1e-12) and q.sdm == pytest.approx(0, abs=1e-12)


def test_shift_gives_chamfer_of_twice_the_squared_shift_and_hausdorff_of_the_shift():
    x = sphere(1_000)
    shifted = x + [0, 0, 1e-4]  # tiny shift: each point's nearest neighbour is its twin
    assert chamfer_distance(x, shifted) == pytest.approx(2 * 1e-8, rel=1e-3)
    assert hausdorff_distance(x, shifted) == pytest.approx(1e-4, rel=1e-3)


def test_subset_has_zero_backward_term():
    x = sphere(1_000)
    subset = x[::4]
    expected = np.mean(np.min(cdist(x, subset, "sqeuclidean"), axis=1))
    assert chamfer_distance(x, subset) == pytest.approx(expected, rel=1e-9)


def test_subset_hausdorff_matches_brute_force():
    x = sphere(1_000)
    subset = x[::4]
    expected = np.max(np.min(cdist(x, subset), axis=1))  # subset -> x is 0: every subset point is in x
    assert hausdorff_distance(x, subset) == pytest.approx(expected, rel=1e-9)
    assert hausdorff_distance(subset, x) == pytest.approx(expected, rel=1e-9)


def test_normal_consistency_of_flipped_and_perpendicular_normals():
    x = sphere(500)
    normals = x.copy()  # outward unit normals of the sphere
    assert normal_consistency(x, x, normals, normals, oriented=True) == pytest.approx(0, abs=1e-12)
    assert normal_consistency(x, x, normals, -normals, oriented=True) == pytest.approx(2)  # worst oriented
    assert normal_consistency(x, x, normals, -normals) == pytest.approx(0, abs=1e-12)  # unoriented: a flip is the same plane
    perpendicular = np.cross(normals, [0.0, 0.0, 1.0])
    assert normal_consistency(x, x, normals, perpendicular) == pytest.approx(1)  # worst


def test_normal_consistency_of_pca_normals_on_a_sphere_is_small():
    x = sphere(2_000)
    assert normal_consistency(x, x[::2]) < 0.05


def test_sdm_grows_with_noise():
    x = sphere(2_000)
    rng = np.random.default_rng(1)
    scores = [quality(x, x + rng.normal(scale=s, size=x.shape)).sdm for s in (1e-3, 1e-2, 5e-2)]
    assert 0 < scores[0] < scores[1] < scores[2]
