"""Top curvature points (TCP): exact budgets of core points, highest curvature first, seeded ties."""
import numpy as np

from model.baselines import tcp_simplify
from model.geometry import point_features
from model.selection import Tile

CENTRE = np.array([500_000.0, 4_000_000.0, 100.0])


def wavy_tile(n: int = 6_000, seed: int = 11) -> Tile:
    """A curved sheet, core in the middle of x and halo either side: no two curvatures tie."""
    rng = np.random.default_rng(0)
    xy = rng.uniform(-10, 10, (n, 2))
    xyz = np.c_[xy, 2 * np.sin(xy[:, 0]) * np.cos(0.7 * xy[:, 1])]
    return Tile(xyz, np.abs(xyz[:, 0]) < 7, CENTRE, seed)


def cube_tile(per_face: int = 1_000) -> tuple[Tile, np.ndarray]:
    """Samples on the surface of [-1, 1]^3, all core, and each point's distance to the nearest edge."""
    rng = np.random.default_rng(1)
    faces = [np.insert(rng.uniform(-1, 1, (per_face, 2)), axis, side, axis=1) for axis in range(3) for side in (-1, 1)]
    xyz = np.concatenate(faces)
    to_edge = 1 - np.sort(np.abs(xyz), axis=1)[:, 1]
    return Tile(xyz, np.ones(len(xyz), dtype=bool), CENTRE, seed=3), to_edge


def test_exact_budget_of_unique_core_points():
    tile = wavy_tile()
    for budget in (0, 1, 37, 1_000, tile.core_count, tile.core_count + 5):
        selection = tcp_simplify(tile, budget)
        assert len(selection.indices) == min(budget, tile.core_count)
        assert len(np.unique(selection.indices)) == len(selection.indices)
        assert tile.core[selection.indices].all()
        np.testing.assert_array_equal(selection.xyz, tile.xyz[selection.indices])


def test_deterministic_and_a_prefix_is_the_coarser_result():
    tile = wavy_tile()
    fine = tcp_simplify(tile, 2_000)
    np.testing.assert_array_equal(tcp_simplify(tile, 2_000).indices, fine.indices)
    np.testing.assert_array_equal(tcp_simplify(tile, 200).indices, fine.indices[:200])


def test_order_is_decreasing_curvature_estimated_over_core_and_halo():
    tile = wavy_tile()
    selection = tcp_simplify(tile, 500)
    core = np.flatnonzero(tile.core)
    kappa = point_features(tile.xyz).kappa
    np.testing.assert_array_equal(kappa[selection.indices], np.sort(kappa[core])[::-1][:500])
    core_only = np.zeros(len(tile.xyz), dtype=np.float32)  # what a core-only estimate would rank instead
    core_only[core] = point_features(tile.xyz[core]).kappa
    assert not np.array_equal(core_only[selection.indices], np.sort(core_only[core])[::-1][:500])


def test_cube_edges_come_first():
    tile, to_edge = cube_tile()
    selection = tcp_simplify(tile, 300)  # 5 % of the points; 28 % lie within 0.15 of an edge
    assert to_edge[selection.indices].max() < 0.15
    assert np.median(to_edge[selection.indices]) < 0.05


def test_ties_fall_in_a_seeded_order():
    rng = np.random.default_rng(2)
    xyz = np.c_[rng.uniform(-5, 5, (3_000, 2)), np.zeros(3_000)]  # a plane: kappa is exactly 0 everywhere
    core = np.abs(xyz[:, 0]) < 4
    first = tcp_simplify(Tile(xyz, core, CENTRE, seed=11), 500).indices
    np.testing.assert_array_equal(tcp_simplify(Tile(xyz, core, CENTRE, seed=11), 500).indices, first)
    assert not np.array_equal(tcp_simplify(Tile(xyz, core, CENTRE, seed=12), 500).indices, first)
    picked = np.zeros(len(xyz), dtype=bool)
    picked[first] = True
    left = (xyz[:, 0] < 0) & core
    assert 0.4 < picked[left].sum() / 500 < 0.6  # a uniform sample of the flat core, not one clump
