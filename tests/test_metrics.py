"""Analytic cases for the paper's metrics."""
import numpy as np
import pytest

from model.metrics import chamfer_distance, quality


def sphere(n: int, seed: int = 0) -> np.ndarray:
    v = np.random.default_rng(seed).normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def test_identical_clouds_score_zero():
    x = sphere(2_000)
    q = quality(x, x)
    assert q.chamfer == 0 and q.curvature_error == 0 and q.roughness_error == 0


def test_shift_gives_chamfer_of_twice_the_squared_shift():
    x = sphere(1_000)
    assert chamfer_distance(x, x + [0, 0, 1e-4]) == pytest.approx(2 * 1e-8, rel=1e-3)  # tiny shift: NN is the twin


def test_subset_has_zero_backward_term():
    x = sphere(1_000)
    subset = x[::4]
    forward = chamfer_distance(x, subset)
    from scipy.spatial import cKDTree

    expected = np.mean(np.square(cKDTree(subset).query(x)[0]))
    assert forward == pytest.approx(expected, rel=1e-9)
