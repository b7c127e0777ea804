"""Point geometry (paper section 3.1) on analytic shapes: planes, spheres, cubes, scaled and shifted copies."""
import numpy as np
import pytest

from model import geometry
from pykdtree.kdtree import KDTree

from model.geometry import (PointTree, bandwidth, curvature, knn, local_eigenvalues, local_features, local_frames,
                            mean_curvature, nearest_member, neighbours, point_features, roughness)
from model.rules import (capped_twins, column_max, column_mean, column_min, grid_xyz, morton_order, most_twins,
                         stable_argsort)
from tiling.plan import DensityGrid


def plane(n: int = 3_000, noise: float = 0.0, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.c_[rng.uniform(-1, 1, (n, 2)), rng.normal(0, noise, n) if noise else np.zeros(n)]


def sphere(n: int = 3_000, radius: float = 2.0) -> np.ndarray:
    """Fibonacci-lattice samples: uniform over the sphere with near-equal spacing, so kappa is near-constant."""
    i = np.arange(n) + 0.5
    polar, azimuth = np.arccos(1 - 2 * i / n), np.pi * (1 + 5**0.5) * i
    return radius * np.c_[np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)]


def cube(per_face: int = 1_000, seed: int = 0) -> np.ndarray:
    """Uniform samples on the surface of [-1, 1]^3."""
    rng = np.random.default_rng(seed)
    faces = [np.insert(rng.uniform(-1, 1, (per_face, 2)), axis, side, axis=1) for axis in range(3) for side in (-1, 1)]
    return np.concatenate(faces)


def wavy(n: int = 3_000, seed: int = 1) -> np.ndarray:
    """A curved sheet with varying curvature, so every feature varies from point to point."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-1, 1, (n, 2))
    return np.c_[xy, 0.3 * np.sin(3 * xy[:, 0]) * np.cos(2 * xy[:, 1])]


def test_plane_is_flat_with_vertical_normals():
    features = point_features(plane())
    assert features.kappa.max() < 1e-12
    np.testing.assert_allclose(np.abs(features.normals[:, 2]), 1, atol=1e-6)
    noisy = point_features(plane(noise=1e-4))
    assert noisy.kappa.max() < 1e-3
    assert np.abs(noisy.normals[:, 2]).min() > 0.99


def test_sphere_has_even_curvature_above_the_plane_and_radial_normals():
    xyz = sphere()
    features = point_features(xyz)
    kappa = features.kappa
    assert kappa.std() / kappa.mean() < 0.1
    assert kappa.min() > 10 * point_features(plane(noise=1e-4)).kappa.max()
    radial = np.einsum("ij,ij->i", features.normals, xyz / np.linalg.norm(xyz, axis=1, keepdims=True))
    assert np.abs(radial).min() > 0.99


def test_sphere_curvature_grows_as_the_squared_spacing_over_radius():
    base = np.median(point_features(sphere(3_000, radius=2.0)).kappa)
    smaller = np.median(point_features(sphere(750, radius=1.0)).kappa)  # same spacing, half the radius
    denser = np.median(point_features(sphere(12_000, radius=2.0)).kappa)  # same radius, half the spacing
    assert 3.5 < smaller / base < 4.5
    assert 3.5 < base / denser < 4.5


def test_cube_edges_and_corners_are_more_curved_than_faces():
    xyz = cube()
    kappa = point_features(xyz).kappa
    folded = np.sort(np.abs(xyz), axis=1)  # column 2 is 1 on the surface
    to_edge = 1 - folded[:, 1]
    to_corner = np.hypot(1 - folded[:, 1], 1 - folded[:, 0])
    face = np.median(kappa[to_edge > 0.3])
    edge = np.median(kappa[(to_edge < 0.02) & (to_corner > 0.3)])
    corner = np.median(kappa[to_corner < 0.05])
    assert face < 1e-6
    assert edge > 0.05 and edge > 5 * face
    # With the paper's covariance about the point, corners score like edges, not clearly above them
    # (corner/edge median ratio 0.88-1.26 over 8 sampled cubes; about the mean, 1.3-1.9).
    assert corner > 0.7 * edge


def test_local_frames_match_lapack_on_every_kind_of_neighbourhood():
    rng = np.random.default_rng(2)
    line = np.c_[np.linspace(0, 5, 300), 1e-6 * rng.normal(size=(300, 2))]  # two near-zero eigenvalues
    blob = rng.normal(size=(300, 3)) + 10  # near-isotropic
    xyz = np.concatenate([wavy(1_000), line + 5, blob, 1e-3 * sphere(300)])
    nbrs = knn(xyz, 12)
    eigenvalues, normals = local_frames(xyz, nbrs)
    offsets = xyz[nbrs.indices] - xyz[:, None, :]  # the paper's covariance, about the point
    reference, frames = np.linalg.eigh(offsets.transpose(0, 2, 1) @ offsets)
    scale = reference.sum(axis=1, keepdims=True)
    np.testing.assert_allclose(eigenvalues / scale, reference / scale, atol=1e-11)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1, atol=1e-6)
    distinct = (reference[:, 1] - reference[:, 0]) > 1e-3 * scale[:, 0]  # where the normal is well defined
    agreement = np.abs(np.einsum("ij,ij->i", normals, frames[:, :, 0]))
    assert agreement[distinct].min() > 1 - 1e-6
    np.testing.assert_array_equal(local_eigenvalues(xyz, nbrs), eigenvalues)  # the survey's path, without normals


def test_chunking_does_not_change_features(monkeypatch):
    xyz = wavy(2_000)
    whole = point_features(xyz)
    monkeypatch.setattr(geometry, "QUERY_POINTS", 300)
    monkeypatch.setattr(geometry, "FRAME_POINTS", 300)
    chunked = point_features(xyz)
    np.testing.assert_array_equal(whole.nbrs.indices, chunked.nbrs.indices)
    np.testing.assert_array_equal(whole.kappa, chunked.kappa)
    np.testing.assert_array_equal(whole.mean_curvature, chunked.mean_curvature)


def test_mean_curvature_is_the_gaussian_weighted_average_of_the_paper():
    xyz = wavy(500)
    nbrs = knn(xyz, 10)
    kappa = point_features(xyz, 10).kappa
    h = 0.01
    expected = np.empty(len(xyz))
    for i in range(len(xyz)):
        neighbours = nbrs.indices[i]
        w = np.exp(-np.sum((xyz[neighbours] - xyz[i]) ** 2, axis=1) / h)
        expected[i] = np.sum(kappa[neighbours] * w) / np.sum(w)
    np.testing.assert_allclose(mean_curvature(kappa, nbrs, h), expected, rtol=1e-4)


def test_mean_curvature_smooths():
    xyz = wavy()
    nbrs = knn(xyz)
    h = bandwidth(nbrs)
    constant = np.full(len(xyz), 0.07, dtype=np.float32)
    np.testing.assert_allclose(mean_curvature(constant, nbrs, h), 0.07, rtol=1e-6)
    kappa = np.random.default_rng(3).uniform(0, 1 / 3, len(xyz)).astype(np.float32)
    kbar = mean_curvature(kappa, nbrs, h)
    around = kappa[nbrs.indices]
    assert (kbar >= around.min(axis=1) - 1e-6).all() and (kbar <= around.max(axis=1) + 1e-6).all()
    assert np.abs(kbar - kappa).mean() > 0.01  # it does average, not just copy kappa


def test_roughness_is_where_curvature_departs_from_its_neighbourhood():
    """A point on a cube's edge is more curved than the mean of its neighbours (half of them on the flat
    faces): rough. A point in a face's middle, among flat neighbours, is not. A constant field has none."""
    xyz = cube(per_face=2_000)
    features = point_features(xyz)
    to_edge = np.sort(1 - np.abs(xyz), axis=1)[:, 1]  # distance to the nearest edge (0 on an edge)
    on_edge, in_middle = to_edge < 0.02, to_edge > 0.5
    assert np.median(features.roughness[on_edge]) > 20 * max(np.median(features.roughness[in_middle]), 1e-9)
    assert np.median(features.roughness[on_edge]) > 0.3 * np.median(features.kappa[on_edge])
    constant = np.full(100, 0.05)
    np.testing.assert_array_equal(roughness(constant, constant), 0.0)


def test_sphere_is_smooth():
    features = point_features(sphere())
    assert np.median(features.roughness) < 0.05 * np.median(features.kappa)
    assert features.roughness.max() < 0.2 * np.median(features.kappa)


def test_bandwidth_follows_local_spacing():
    xyz = wavy()
    h = bandwidth(knn(xyz))
    np.testing.assert_allclose(bandwidth(knn(1000 * xyz)), 1e6 * h, rtol=1e-5)
    sparse, dense = plane(400, seed=4), plane(6_400, seed=5)
    assert np.median(bandwidth(knn(sparse))) > 10 * np.median(bandwidth(knn(dense)))


@pytest.mark.parametrize("transform", ["scaled", "shifted", "shifted-then-centred"])
def test_features_are_scale_and_offset_invariant(transform):
    xyz = wavy()
    moved = {
        "scaled": 1000 * xyz,
        "shifted": xyz + [5e5, 4e6, 100.0],
        "shifted-then-centred": (xyz + [5e5, 4e6, 100.0]) - (xyz + [5e5, 4e6, 100.0]).mean(axis=0),
    }[transform]
    base, other = point_features(xyz), point_features(moved)
    np.testing.assert_array_equal(base.nbrs.indices, other.nbrs.indices)
    np.testing.assert_allclose(other.kappa, base.kappa, rtol=1e-4, atol=1e-8)
    np.testing.assert_allclose(other.mean_curvature, base.mean_curvature, rtol=1e-4, atol=1e-8)
    np.testing.assert_allclose(other.roughness, base.roughness, atol=1e-6)
    assert np.abs(np.einsum("ij,ij->i", base.normals, other.normals)).min() > 1 - 1e-5


def test_all_points_identical_gives_no_nan():
    features = point_features(np.full((50, 3), 7.5))
    for values in (features.normals, features.kappa, features.mean_curvature, features.roughness):
        assert np.isfinite(values).all()
    np.testing.assert_array_equal(features.kappa, 0)
    np.testing.assert_allclose(np.linalg.norm(features.normals, axis=1), 1, atol=1e-6)


def test_the_point_itself_comes_first_among_duplicates():
    xyz = np.repeat(wavy(200), 3, axis=0)  # every point three times: the tree may list a twin first
    nbrs = knn(xyz, 8)
    np.testing.assert_array_equal(nbrs.indices[:, 0], np.arange(len(xyz)))
    assert (nbrs.sq_dist[:, :3] == 0).all()
    assert all(len(set(row)) == len(row) for row in nbrs.indices.tolist())
    many = knn(np.repeat(wavy(20), 10, axis=0), 4)  # more twins than k: the point may not be listed at all
    np.testing.assert_array_equal(many.indices[:, 0], np.arange(200))
    features = point_features(xyz)
    assert np.isfinite(features.mean_curvature).all()


def spot_of_twins(twins: int = 2_000, seed: int = 1) -> np.ndarray:
    """A curved sheet with a scanner's no-return spot: `twins` exact copies of one point of it, then the sheet."""
    sheet = wavy(3_000, seed)
    return np.concatenate([np.repeat(sheet[:1], twins, axis=0), sheet])


def test_a_tree_holds_k_twins_of_a_position_and_lists_the_whole_clouds_neighbours():
    """pykdtree walks every twin of a position for each of them (quadratic in a no-return spot): PointTree holds
    only k of them, which lists the same distances, and positions, as a tree of every point; a cloud without
    a larger group gets the plain tree."""
    xyz = spot_of_twins()
    assert most_twins(xyz) == 2_001 and most_twins(wavy()) == 1 and most_twins(np.empty((0, 3))) == 0
    latent = np.repeat(np.random.default_rng(2).normal(size=(500, 1)), 8, axis=1)  # equal columns cannot cancel
    assert most_twins(latent) == 1 and most_twins(np.concatenate([latent, latent[:3]])) == 2
    held = capped_twins(xyz, 16)
    assert len(held) == len(xyz) - 2_001 + 16 and (np.diff(held) > 0).all()
    assert PointTree.of(xyz, 16).held is not None and PointTree.of(wavy(), 16).held is None
    capped = neighbours(PointTree.of(xyz, 16), xyz, np.arange(len(xyz)), 16)
    plain = neighbours(PointTree(KDTree(xyz), None, 16), xyz, np.arange(len(xyz)), 16)
    np.testing.assert_array_equal(capped.sq_dist, plain.sq_dist)
    np.testing.assert_array_equal(xyz[capped.indices], xyz[plain.indices])
    np.testing.assert_array_equal(capped.indices[:, 0], np.arange(len(xyz)))
    with pytest.raises(ValueError, match="17 neighbours asked of a tree built for 16"):
        PointTree.of(xyz, 16).query(xyz, 17)  # past its k, a capped tree would lose twins at distance 0
    for k in (1, 2):  # nearest and nearest-other searches
        distance, index = PointTree.of(xyz, k).query(xyz, k, squared=False)
        expected, _ = KDTree(xyz).query(xyz, k)
        np.testing.assert_array_equal(distance, expected)
        np.testing.assert_array_equal(xyz[index], xyz[KDTree(xyz).query(xyz, k)[1]])


def test_features_of_a_spot_of_twins_are_those_of_a_tree_holding_every_twin():
    """Which twin a capped tree lists changes no feature: the spot's twins are flat (their neighbours all at
    distance 0), and every other point's neighbours lie at the same positions."""
    xyz = spot_of_twins()
    features = point_features(xyz)
    nbrs = neighbours(PointTree(KDTree(xyz), None, 16), xyz, np.arange(len(xyz)), 16)
    kappa = curvature(local_eigenvalues(xyz, nbrs))
    np.testing.assert_array_equal(features.kappa, kappa)
    np.testing.assert_array_equal(features.mean_curvature, mean_curvature(kappa, nbrs, bandwidth(nbrs)))
    assert (features.kappa[:2_001] == 0).all()
    members = np.arange(0, len(xyz), 2)  # nearest member: the spot's twins find one of theirs at the spot
    found = nearest_member(xyz, members, np.arange(len(xyz)))
    np.testing.assert_array_equal(xyz[members[found]], xyz[members[KDTree(xyz[members]).query(xyz, 1)[1]]])


def test_k_is_clipped_to_the_point_count():
    nbrs = knn(wavy(5), 16)
    assert nbrs.indices.shape == nbrs.sq_dist.shape == (5, 5)
    assert np.isfinite(point_features(wavy(2)).kappa).all()


def test_curvature_is_zero_for_zero_eigenvalues():
    kappa = curvature(np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.0, 1.0, 3.0]]))
    np.testing.assert_allclose(kappa, [0, 1 / 3, 0])


def test_knn_matches_brute_force_on_shuffled_points():
    xyz = np.random.default_rng(11).normal(size=(3_000, 3)) * [50.0, 20.0, 1.0]
    found = knn(xyz, 8)
    squared = ((xyz[:, None, :] - xyz[None, :, :]) ** 2).sum(-1)
    expected = np.sort(squared, axis=1)[:, :8]
    assert np.allclose(found.sq_dist, expected, rtol=1e-5, atol=1e-9)
    assert np.allclose(squared[np.arange(len(xyz))[:, None], found.indices], expected, rtol=1e-5, atol=1e-9)


def test_morton_order_is_a_permutation_that_keeps_neighbours_close():
    grid = np.stack(np.meshgrid(*[np.arange(16.0)] * 3, indexing="ij"), -1).reshape(-1, 3)
    shuffled = grid[np.random.default_rng(3).permutation(len(grid))]
    order = morton_order(shuffled)
    assert np.array_equal(np.sort(order), np.arange(len(grid)))
    assert np.abs(np.diff(shuffled[order], axis=0)).sum(1).mean() < 2.5  # shuffled: about 16


def test_local_features_of_a_tile_core_are_the_whole_clouds_and_query_only_two_rings():
    """The core of a tile inside a wide halo: kappa, mean curvature and neighbours of the core rows (and mean
    curvature of their neighbours) as point_features gives them on every point, duplicates included,
    from queries of the core and the two rings of neighbours its mean curvature reaches, not the halo."""
    xyz = np.concatenate([wavy(20_000, seed=3) * [10, 10, 1], wavy(2_000, seed=3)[:300] * [10, 10, 1]])
    core = np.flatnonzero((np.abs(xyz[:, 0]) < 3) & (np.abs(xyz[:, 1]) < 3))
    whole, local = point_features(xyz), local_features(xyz, core)
    np.testing.assert_array_equal(local.nbrs.indices, whole.nbrs.indices[core])
    reached = np.unique(whole.nbrs.indices[core])
    np.testing.assert_array_equal(local.mean_curvature[reached], whole.mean_curvature[reached])
    np.testing.assert_array_equal(local.kappa[np.unique(whole.nbrs.indices[reached])],
                                  whole.kappa[np.unique(whole.nbrs.indices[reached])])
    set_rows = np.flatnonzero(local.kappa != 0)
    assert len(core) < len(set_rows) < 0.5 * len(xyz)  # the halo beyond two rings was never queried
    empty = local_features(xyz, np.empty(0, dtype=np.int64))
    assert empty.nbrs.indices.shape == (0, 16) and not empty.kappa.any()


@pytest.mark.parametrize("dtype", [np.float64, np.float32, np.int64, np.int32])
def test_column_bounds_are_numpys_axis_reductions(dtype):
    """The fast per-column bounds (model.rules) return exactly what min/max over axis 0 return: dtype,
    values, a NaN where a column holds one, and numpy's error on an empty array."""
    rng = np.random.default_rng(1)
    values = (rng.normal(0, 1e6, (1_000, 3))).astype(dtype)
    for narrow in (values, values[:, :2], values[::3]):
        for ours, numpys in ((column_min(narrow), narrow.min(axis=0)), (column_max(narrow), narrow.max(axis=0))):
            assert ours.dtype == numpys.dtype and np.array_equal(ours, numpys)
    if np.issubdtype(dtype, np.floating):
        values[5, 1] = np.nan
        assert np.isnan(column_min(values)[1]) and not np.isnan(column_min(values)[[0, 2]]).any()
    with pytest.raises(ValueError):
        column_min(values[:0])


def test_column_mean_is_numpys_axis_mean_bit_for_bit():
    """A tile's centre (pipeline.engine.tasks.load_tile) comes from column_mean: it must equal mean(axis=0)
    exactly, or every centred coordinate, and so the picks, would move by round-off."""
    rng = np.random.default_rng(2)
    for count in (1, 7, 1_000, 31_000, 200_001):
        values = rng.normal(0, 1, (count, 3)) * rng.uniform(0.01, 1e5) + rng.uniform(-1e6, 1e6, 3)
        for narrow in (values, values[::3], values[rng.random(count) < 0.6]):
            if len(narrow):
                assert np.array_equal(column_mean(narrow), narrow.mean(axis=0))


def test_coordinates_of_records_and_their_grid_cells_are_the_broadcast_formulas():
    """grid_xyz and the grid's cell rule work an axis at a time for speed; the values must be those of the
    plain (n, 3) formulas to the last bit, or tiles would own different points."""
    rng = np.random.default_rng(2)
    records = np.zeros(5_000, dtype=[("X", "<i4"), ("Y", "<i4"), ("Z", "<i4"), ("intensity", "<u2")])
    for name in "XYZ":
        records[name] = rng.integers(-10**7, 10**7, len(records))
    scales, offsets = np.array([0.001, 0.003, 0.00025]), np.array([687_123.4, 4_810_987.6, -12.5])
    xyz = grid_xyz(records, scales, offsets)
    expected = np.column_stack([records[name] for name in "XYZ"]).astype(np.float64) * scales + offsets
    assert np.array_equal(xyz, expected)
    grid = DensityGrid.covering(xyz.min(axis=0) + 500, xyz.max(axis=0) - 500, tile_size=37.0)
    flat = np.floor((xyz[:, :2] - np.asarray(grid.origin)) / grid.cell)
    ij = [np.clip(flat[:, a], 0, grid.shape[a] - 1).astype(np.int64) for a in (0, 1)]
    assert np.array_equal(grid.cell_of(xyz), ij[0] * grid.shape[1] + ij[1])


@pytest.mark.parametrize("count, distinct", [(0, 1), (1, 1), (2, 1), (1_000, 7), (50_000, 2**60), (50_000, 40_000)])
def test_stable_argsort_is_numpys_stable_argsort(count, distinct):
    """The default (vectorised) sort with runs of equal keys put back in index order: the stable order,
    whether keys are all equal, mostly tied, or distinct (as a Z-order curve's codes nearly are)."""
    keys = np.random.default_rng(count).integers(0, distinct, count).astype(np.uint64)
    np.testing.assert_array_equal(stable_argsort(keys), np.argsort(keys, kind="stable"))


def test_morton_order_keeps_file_order_among_points_of_one_code():
    """Points closer than 2**-21 of the extent share a code; among them the order is the points' own."""
    xyz = np.repeat(np.random.default_rng(3).uniform(0, 10, (300, 3)), 4, axis=0)[::-1].copy()
    runs = morton_order(xyz).reshape(300, 4)  # each point's four copies in a row, lowest index first
    assert (np.diff(runs, axis=1) == 1).all()


def test_nearest_member_is_the_tree_search_with_members_their_own():
    """Members answer themselves; every other query gets the member a full search of the members finds."""
    from pykdtree.kdtree import KDTree
    xyz = plane(2_000, noise=0.01, seed=4)
    members = np.random.default_rng(1).choice(len(xyz), 300, replace=False)
    queries = np.arange(0, len(xyz), 3)
    found = nearest_member(xyz, members, queries)
    _, searched = KDTree(xyz[members]).query(xyz[queries], k=1)
    assert np.array_equal(found, searched)
    is_member = np.isin(queries, members)
    assert is_member.any() and np.array_equal(members[found[is_member]], queries[is_member])
