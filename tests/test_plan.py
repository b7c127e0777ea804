"""Tile plan and budgets: the cores partition the scan, dense tiles split, budgets sum exactly."""
import numpy as np
import pytest

from model.rules import kept_count
from tiling.budgets import grouped_budgets, shared_budgets, tile_budgets
from tiling.plan import SUB_CELLS, DensityGrid, crowded_cells, plan_tiles


def clustered_points(n: int, seed: int = 0) -> np.ndarray:
    """Uniform background plus one very dense cluster, so some tiles must split."""
    rng = np.random.default_rng(seed)
    background = rng.uniform([0, 0, 0], [200, 120, 10], size=(n // 2, 3))
    cluster = rng.normal([50, 60, 2], [3, 3, 1], size=(n - n // 2, 3))
    return np.vstack([background, cluster])


def test_every_point_in_exactly_one_core_even_on_edges():
    xyz = clustered_points(50_000)
    grid = DensityGrid.covering(xyz.min(0), xyz.max(0), tile_size=25)
    # points exactly on cell and tile boundaries, and on the far edges of the extent
    edges = np.array([[grid.origin[0] + k * grid.cell, grid.origin[1] + 3 * grid.cell, 0] for k in range(0, 40)])
    corner = np.array([xyz.max(0), xyz.min(0)])
    xyz = np.vstack([xyz, edges, corner])
    plan = plan_tiles(grid, *grid.count([xyz]), max_points=2_000)
    owner = plan.tile_of(xyz)
    assert (owner >= 0).all()
    counts = np.bincount(owner, minlength=len(plan.tiles))
    assert counts.sum() == len(xyz)
    assert [t.count for t in plan.tiles] == counts.tolist()
    # the owner's half-open rectangle contains the point (clipped at the far edges of the extent)
    b = np.array([plan.bounds(t) for t in range(len(plan.tiles))])[owner]
    inside = (xyz[:, 0] >= b[:, 0]) & (xyz[:, 1] >= b[:, 1]) & ((xyz[:, 0] < b[:, 2]) | np.isclose(xyz[:, 0], xyz[:, 0].max()))
    assert inside.all()


def test_dense_tiles_split_until_under_budget():
    xyz = clustered_points(80_000)
    grid = DensityGrid.covering(xyz.min(0), xyz.max(0), tile_size=50)
    plan = plan_tiles(grid, *grid.count([xyz]), max_points=3_000)
    single_cell = [(t.i1 - t.i0) * (t.j1 - t.j0) == 1 for t in plan.tiles]
    assert all(t.count <= 3_000 or one for t, one in zip(plan.tiles, single_cell))
    assert len(plan.tiles) > (200 // 50 + 1) * (120 // 50 + 1)  # more tiles than the nominal grid
    assert all(t.count > 0 for t in plan.tiles)


def test_a_crowded_cell_is_split_on_its_sub_cells_into_tiles_under_the_limit():
    """A scanner's standpoint: 20,000 points within 0.8 m, in one 3.125 m cell of a 25 m tile. Its
    sub-cells (tile size / 512) are quartered like cells, so every tile holds at most the limit; the cores
    still partition every point (sub-cell edges included), and each point lies in its tile's rectangle."""
    rng = np.random.default_rng(4)
    background = rng.uniform([0, 0, 0], [100, 100, 5], size=(20_000, 3))
    standpoint = rng.normal([40.2, 60.2, 1], [0.2, 0.2, 0.5], size=(20_000, 3))
    xyz = np.vstack([background, standpoint])
    grid = DensityGrid.covering(xyz.min(0), xyz.max(0), tile_size=25)
    sub = grid.cell / SUB_CELLS
    edges = np.array([[40 + k * sub, 60.2, 0.0] for k in range(-20, 20)])  # on and around sub-cell edges
    xyz = np.vstack([xyz, edges])
    cells, counts = grid.count([xyz])
    crowded = crowded_cells(cells, counts, 2_000)
    assert len(crowded) >= 1
    plan = plan_tiles(grid, cells, counts, 2_000, grid.sub_count(xyz, crowded))
    assert all(0 < t.count <= 2_000 for t in plan.tiles)
    owner = plan.tile_of(xyz)
    assert (owner >= 0).all() and np.bincount(owner, minlength=len(plan.tiles)).tolist() == [t.count for t in plan.tiles]
    b = np.array([plan.bounds(t) for t in range(len(plan.tiles))])[owner]
    slack = 1e-9 * np.abs(xyz[:, :2]).max()  # a sub-cell's bounds are summed from the cell's, not floored
    assert ((xyz[:, 0] >= b[:, 0] - slack) & (xyz[:, 0] < b[:, 2] + slack)
            & (xyz[:, 1] >= b[:, 1] - slack) & (xyz[:, 1] < b[:, 3] + slack)).all()
    parts = [t for t in plan.tiles if t.sub is not None]
    assert len(parts) >= 10  # 20,000 points over 2,000 a tile
    assert sum(t.occupied for t in parts) <= len(crowded)  # the split cells' area, no more
    assert plan.per_tile(counts, grid.sub_count(xyz, crowded)).tolist() == [t.count for t in plan.tiles]
    unsplit = plan_tiles(grid, cells, counts, 2_000)  # without sub-cell counts: the old plan, a tile per crowded cell
    assert max(t.count for t in unsplit.tiles) > 2_000 and all(t.sub is None for t in unsplit.tiles)


def test_a_split_cells_tiles_share_the_budget_the_whole_cell_would_get():
    """Tiles grouped (a crowded cell split for memory) get together what the cell would as one tile,
    shared in proportion to their weights; ungrouped tiles are budgeted exactly as by tile_budgets."""
    counts = np.array([500, 4_000, 3_000, 1_000, 10, 700])
    floors = np.array([50, 40, 40, 40, 5, 60])
    weights = np.array([600.0, 4_400, 3_300, 1_100, 10, 700])
    groups = np.array([0, 1, 1, 1, 4, 5])  # tiles 1-3: one cell's parts
    grouped = grouped_budgets(counts, 0.1, groups, floors, weights)
    whole = tile_budgets(np.array([500, 8_000, 10, 700]), 0.1, np.array([50, 120, 5, 60]),
                         np.array([600.0, 8_800, 10, 700]))
    assert grouped.sum() == kept_count(0.1, int(counts.sum()))
    assert grouped[[0, 4, 5]].tolist() == whole[[0, 2, 3]].tolist() and grouped[1:4].sum() == whole[1]
    assert np.abs(grouped[1:4] - whole[1] * weights[1:4] / weights[1:4].sum()).max() < 1  # by weight, not floor
    alone = np.arange(len(counts))
    assert grouped_budgets(counts, 0.1, alone, floors, weights).tolist() == tile_budgets(counts, 0.1, floors, weights).tolist()
    extra = np.array([30.0, 10, 0, 20, 0, 5])  # holes: a group's are summed, then its parts get theirs on top
    grouped = grouped_budgets(counts, 0.1, groups, floors, weights, extra)
    whole = tile_budgets(np.array([500, 8_000, 10, 700]), 0.1, np.array([50, 120, 5, 60]),
                         np.array([600.0, 8_800, 10, 700]), np.array([30.0, 30, 0, 5]))
    assert grouped.sum() == kept_count(0.1, int(counts.sum())) and grouped[1:4].sum() == whole[1]
    rate = (whole[1] - 30) / weights[1:4].sum()
    assert np.abs(grouped[1:4] - (rate * weights[1:4] + extra[1:4])).max() < 1


def test_all_identical_points_make_one_tile():
    xyz = np.tile([[10.0, 20.0, 3.0]], (500, 1))
    grid = DensityGrid.covering(xyz.min(0), xyz.max(0), tile_size=50)
    plan = plan_tiles(grid, *grid.count([xyz]), max_points=100)
    assert len(plan.tiles) == 1 and plan.tiles[0].count == 500


@pytest.mark.parametrize("ratio", [1.0, 0.5, 0.1, 0.05, 0.013, 1e-4])
def test_budgets_sum_to_rounded_target(ratio):
    counts = np.random.default_rng(1).integers(0, 5_000, size=97)
    budgets = tile_budgets(counts, ratio)
    assert budgets.sum() == kept_count(ratio, int(counts.sum()))
    assert (budgets <= counts).all() and (budgets >= 0).all()
    assert (np.abs(budgets - ratio * counts) < 1 + 1e-9).all()


@pytest.mark.parametrize("ratio", [1.0, 0.1, 0.013, 1e-3, 1e-5])
def test_floors_keep_sparse_tiles_and_the_exact_total(ratio):
    """A tile never falls below its floor (one point per occupied cell) while the total allows it, the
    total stays exact, and floors beyond the total are scaled down rather than overshooting it."""
    rng = np.random.default_rng(2)
    counts = np.concatenate([rng.integers(1, 6, size=40), rng.integers(5_000, 50_000, size=20)])
    floors = np.minimum(counts, rng.integers(1, 30, size=len(counts)))
    budgets = tile_budgets(counts, ratio, floors)
    target = kept_count(ratio, int(counts.sum()))
    assert budgets.sum() == target and (budgets <= counts).all() and (budgets >= 0).all()
    if floors.sum() <= target:
        assert (budgets >= floors).all()
        plain = tile_budgets(counts, ratio)
        assert (plain[:40] == 0).any() or ratio >= 0.1  # without floors the smallest tiles round to nothing
    else:
        assert (budgets <= floors).all()


@pytest.mark.parametrize("ratio", [0.5, 0.1, 0.01])
def test_extras_add_to_one_fill_rate_and_the_total_stays_exact(ratio):
    """Quotas c * weight + extra: tiles away from their floors and counts keep one rate c per unit of weight
    above their extras (one fill rate across the scan), the total is exact, and extras beyond it are
    scaled down rather than overshooting it."""
    rng = np.random.default_rng(4)
    counts = rng.integers(2_000, 40_000, size=30)
    weights = counts * rng.uniform(1.0, 2.5, size=len(counts))
    extra = np.where(rng.random(len(counts)) < 0.3, rng.uniform(0, 0.1 * ratio * counts), 0.0)
    budgets = tile_budgets(counts, ratio, np.ones_like(counts), weights, extra)
    target = kept_count(ratio, int(counts.sum()))
    assert budgets.sum() == target and (budgets <= counts).all()
    rate = (target - extra.sum()) / weights.sum()
    assert (np.abs(budgets - (rate * weights + extra)) < 1 + 1e-9).all()  # one rate, up to the integer rounding
    assert (tile_budgets(counts, ratio, np.ones_like(counts), weights, 0 * extra)
            == tile_budgets(counts, ratio, np.ones_like(counts), weights)).all()
    crowded = tile_budgets(counts, ratio, np.ones_like(counts), weights, np.full(len(counts), float(counts.max())))
    assert crowded.sum() == target and (crowded <= counts).all()


def test_budgets_are_the_clipped_rate_a_bisection_finds_whatever_the_floors_counts_and_extras():
    """Quotas min(count, max(floor, c * weight + extra)) summing to the target, against c found by bisection, on
    small adversarial tiles: floors, counts and extras pulling different tiles both ways at once (pinning both
    sides in one pass once gave 1,400 points for a target of 1,250)."""
    rng = np.random.default_rng(11)
    for _ in range(3_000):
        n = int(rng.integers(1, 8))
        counts = rng.integers(0, 50, n)
        floors, weights = rng.integers(0, 20, n), rng.uniform(0.1, 10, n)
        extra = rng.uniform(0, 40, n) * (rng.random(n) < 0.6)
        target = int(rng.integers(0, counts.sum() + 1))
        budgets = shared_budgets(counts, target, floors, weights, extra)
        assert budgets.sum() == target and (budgets >= 0).all() and (budgets <= counts).all()
        lowest = np.minimum(np.maximum(np.minimum(floors, counts), extra), counts)
        if lowest.sum() >= target:
            continue
        clipped = lambda rate: np.minimum(counts, np.maximum(np.minimum(floors, counts), rate * weights + extra))
        low, high = 0.0, 1.0
        while clipped(high).sum() < target:
            high *= 2
        for _ in range(200):
            middle = (low + high) / 2
            low, high = (low, middle) if clipped(middle).sum() >= target else (middle, high)
        assert (np.abs(budgets - clipped(high)) < 1 + 1e-6).all() and (budgets >= np.minimum(floors, counts)).all()
    assert tile_budgets(np.array([2_000, 500]), 0.5, np.array([900, 1]), np.array([2_000.0, 2_000.0]),
                        np.array([0.0, 100.0])).tolist() == [900, 350]


def test_hole_voxels_are_the_voxels_a_trial_fill_missed():
    """A dense plane with a sparse strip: picks of the dense part leave the strip's voxels empty; counted on the
    core's grid (a subset's own minimum would shift its grid), at a voxel edge of sqrt(pi) x the radius."""
    from tiling.budgets import DISC_EDGE, hole_voxels, occupied_voxels

    rng = np.random.default_rng(9)
    plane = np.column_stack([rng.uniform([0, 0], [10, 10], size=(20_000, 2)), np.zeros(20_000)])
    strip = np.column_stack([rng.uniform([10, 0], [20, 10], size=(300, 2)), np.zeros(300)])
    core = np.concatenate([plane, strip]) + [3.3, -7.1, 2.0]
    picks = core[:20_000:10]  # the plane's points only
    sizes = 0.25 * 2.0 ** np.arange(0, 5)
    origin = core.min(axis=0)
    occupied, filled = occupied_voxels(core, sizes, origin), occupied_voxels(picks, sizes, origin)
    assert (filled <= occupied).all() and (occupied_voxels(picks, sizes) != filled).any()
    radius = sizes[2] / DISC_EDGE
    edge = sizes[2]
    expected = len(set(map(tuple, np.floor((core - origin) / edge).astype(int))) -
                   set(map(tuple, np.floor((picks - origin) / edge).astype(int))))
    holes = hole_voxels(occupied[None, :], filled[None, :], sizes, radius)
    assert holes[0] == pytest.approx(expected)
    assert 0.8 * 10 * 10 / edge**2 < expected <= 10 * 10 / edge**2 + 2 * 10 / edge + 1  # the strip's voxels


def test_floors_are_occupied_cells():
    xyz = np.array([[0.5, 0.5, 0], [0.6, 0.5, 0], [3.5, 0.5, 0], [90.0, 90.0, 0]])
    grid = DensityGrid.covering(xyz.min(0), xyz.max(0), tile_size=8)  # 1-unit cells, 8 per tile
    plan = plan_tiles(grid, *grid.count([xyz]), max_points=100)
    assert sorted((t.count, t.occupied) for t in plan.tiles) == [(1, 1), (3, 2)]


def test_target_rounds_half_up():
    assert kept_count(0.5, 3) == 2
    assert kept_count(0.1, 15) == 2
    assert kept_count(1.0, 7) == 7


def test_coverage_weights_give_equal_areas_equal_shares_whatever_their_density():
    """Two 10 x 10 planes, one 20x denser: counts would give the dense one 20x the points, an even spacing
    over both gives them about the same; the weights follow the size at which the total meets the target."""
    from tiling.budgets import coverage_weights, occupied_voxels

    rng = np.random.default_rng(0)
    dense = np.column_stack([rng.uniform(0, 10, size=(40_000, 2)), np.zeros(40_000)])
    sparse = np.column_stack([rng.uniform(0, 10, size=(2_000, 2)), np.zeros(2_000)])
    sizes = 0.5 * 2.0 ** np.arange(-4, 5)
    occupied = np.array([occupied_voxels(dense, sizes), occupied_voxels(sparse, sizes)])
    assert (np.diff(occupied, axis=1) <= 0).all()  # coarser voxels, fewer occupied
    weights = coverage_weights(occupied, sizes, target=800)
    assert abs(weights.sum() - 800) < 0.1 * 800 and 0.8 < weights[0] / weights[1] < 1.25
    budgets = tile_budgets(np.array([40_000, 2_000]), 800 / 42_000, weights=weights)
    assert budgets.sum() == 800 and 0.8 < budgets[0] / budgets[1] < 1.25


def test_saliency_weights_are_the_sums_of_one_pass_keep_weights():
    """Per point 1 + loss / scan mean; per tile the sum: checked against the weights of the points themselves."""
    from tiling.budgets import saliency_weights

    rng = np.random.default_rng(1)
    losses = [rng.exponential(scale, size=n) for scale, n in ((0.01, 300), (0.2, 100), (0.05, 50))]
    counts = np.array([len(loss) for loss in losses])
    levels = np.array([loss.mean() for loss in losses])
    weights, scales = saliency_weights(counts, levels, np.array([(loss / loss.mean()).sum() for loss in losses]))
    scan_mean = np.concatenate(losses).mean()
    np.testing.assert_allclose(weights, [(1 + loss / scan_mean).sum() for loss in losses])
    np.testing.assert_allclose(scales, levels / scan_mean)
    flat, flat_scales = saliency_weights(counts, np.zeros(3), np.zeros(3))
    np.testing.assert_array_equal(flat, counts) and np.testing.assert_array_equal(flat_scales, 0)


def test_pooled_quantile_of_quantile_sketches_matches_the_union():
    from model.geometry import DISTANCE_QUANTILES
    from tiling.budgets import pooled_quantile

    rng = np.random.default_rng(2)
    samples = [rng.lognormal(0, 0.3, 20_000), rng.lognormal(1, 0.3, 5_000), np.empty(0)]
    sketches = [np.quantile(s, DISTANCE_QUANTILES) if len(s) else s for s in samples]
    pooled = pooled_quantile(sketches, np.array([len(s) for s in samples]))
    assert abs(pooled - np.median(np.concatenate(samples))) < 0.03
    assert pooled_quantile([np.empty(0)], np.array([0])) == 0.0
    # samples given by their values, each standing for another size (here 1 and 4 points a value)
    union = np.concatenate([samples[0], np.repeat(samples[1], 4)])
    high = pooled_quantile(samples[:2], np.array([20_000, 20_000]), 0.99)
    assert abs(high - np.quantile(union, 0.99)) < 0.01 * np.quantile(union, 0.99)


def test_far_apart_sites_keep_fine_cells_and_tiles_within_the_budget():
    """Two dense 100 m sites 200 km apart: a dense grid over the extent would have had to coarsen its cells
    (to ~100 m, each holding a whole site); the sparse grid keeps tile_size / 8 cells, so every tile stays
    at or under max_points and only occupied cells are stored."""
    rng = np.random.default_rng(4)
    site = rng.uniform(0, 100, size=(30_000, 2))
    xyz = np.column_stack([np.concatenate([site, site + [200_000.0, 50_000.0]]), np.zeros(60_000)])
    grid = DensityGrid.covering(xyz.min(0), xyz.max(0), tile_size=50)
    assert grid.cell == 50 / 8 and grid.shape[0] > 30_000
    plan = plan_tiles(grid, *grid.count([xyz]), max_points=2_000)
    assert max(t.count for t in plan.tiles) <= 2_000 and sum(t.count for t in plan.tiles) == 60_000
    assert len(plan.cells) <= 2 * 17 * 17  # the cells the two sites cover, not the 10^9 of the extent
    np.testing.assert_array_equal(np.bincount(plan.tile_of(xyz), minlength=len(plan.tiles)),
                                  [t.count for t in plan.tiles])


def test_voxels_at_a_measured_size_are_the_counts_and_fall_between_them():
    from tiling.budgets import occupied_voxels, voxels_at

    rng = np.random.default_rng(6)
    plane = np.column_stack([rng.uniform(0, 10, size=(20_000, 2)), np.zeros(20_000)])
    sizes = 0.25 * 2.0 ** np.arange(0, 4)
    occupied = occupied_voxels(plane, sizes)[None, :]
    np.testing.assert_allclose(voxels_at(occupied, sizes, sizes[2]), occupied[:, 2])
    between = voxels_at(occupied, sizes, sizes[1] * np.sqrt(2))[0]
    assert occupied[0, 2] < between < occupied[0, 1]


def test_voxels_at_are_np_interps_log_log_values_to_the_bit_at_any_size():
    """Every tile at once gives what one np.interp per tile gave (the budgets, and so the kept points, of
    earlier versions), at the measured sizes, between them and past both ends."""
    from tiling.budgets import voxels_at

    rng = np.random.default_rng(8)
    sizes = 0.37 * 2.0 ** np.arange(-8, 9)
    occupied = np.sort(rng.integers(0, 10**6, size=(40, len(sizes))), axis=1)[:, ::-1]
    for size in [*sizes, *rng.uniform(1e-4, 200, 30), 1e-9, 1e6]:
        per_tile = [np.exp(np.interp(np.log(size), np.log(sizes), row)) for row in np.log(np.maximum(occupied, 1e-3))]
        assert np.array_equal(voxels_at(occupied, sizes, size), per_tile), size


def test_even_spacing_is_the_voxel_edge_whose_scan_total_is_the_target():
    from tiling.budgets import even_spacing, occupied_voxels, voxels_at

    rng = np.random.default_rng(7)
    planes = [np.column_stack([rng.uniform(0, 10, size=(n, 2)) + [20 * k, 0], np.zeros(n)])
              for k, n in enumerate((30_000, 3_000))]
    sizes = 0.1 * 2.0 ** np.arange(0, 6)
    occupied = np.array([occupied_voxels(plane, sizes) for plane in planes])
    edge = even_spacing(occupied, sizes, target=1_000)
    assert sizes[0] < edge < sizes[-1]
    assert abs(voxels_at(occupied, sizes, edge).sum() - 1_000) < 0.1 * 1_000


def test_occupied_voxels_count_each_level_as_its_own_grid_would():
    """Counted level from level (the occupied voxels halved), the counts are those of each grid on its own:
    distinct floor((p - low) / size) rows, on a cloud far from the origin with clumps and duplicates."""
    from tiling.budgets import occupied_voxels

    rng = np.random.default_rng(8)
    xyz = np.concatenate([rng.normal(0, 3, size=(5_000, 3)), rng.uniform(-20, 20, size=(2_000, 3))]) + [-7e5, 5e6, -3.1]
    xyz = np.concatenate([xyz, xyz[:500]])
    sizes = 0.37 * 2.0 ** np.arange(-3, 6)
    expected = [len(np.unique(np.floor((xyz - xyz.min(axis=0)) / size), axis=0)) for size in sizes]
    np.testing.assert_array_equal(occupied_voxels(xyz, sizes), expected)
    assert occupied_voxels(xyz[:1], sizes).tolist() == [1] * len(sizes)
    fine = 2.0 ** np.arange(-6, 3)  # a stray return 2**21 finest voxels above the first point: too many for a
    stray = np.concatenate([xyz, xyz[:1] + [0.0, 0.0, 2.0**15]])  # Z-order code, which would take it for that point
    expected = [len(np.unique(np.floor((stray - stray.min(axis=0)) / size), axis=0)) for size in fine]
    np.testing.assert_array_equal(occupied_voxels(stray, fine), expected)
    cube = rng.uniform(0, 1, size=(300, 3))  # one return 2**30 off in every axis: too far even for a row key
    far = np.concatenate([cube, [[2.0**30] * 3]])
    expected = [len(np.unique(np.floor((far - far.min(axis=0)) / size), axis=0)) for size in fine / 4]
    np.testing.assert_array_equal(occupied_voxels(far, fine / 4), expected)
    with pytest.raises(ValueError, match="double"):
        occupied_voxels(xyz, np.array([1.0, 3.0]))


def sparse_beside_dense(seed: int = 8) -> np.ndarray:
    """A 400 x 400 m scan: a sparse field of 16,000 points (250 per nominal 50 m tile, 4,000 per aligned
    square of 4 x 4 of them) and a dense 100 x 100 m block of 60,000 points in one corner."""
    rng = np.random.default_rng(seed)
    field = rng.uniform([0, 0, 0], [400, 400, 5], size=(16_000, 3))
    block = rng.uniform([0, 0, 0], [100, 100, 5], size=(60_000, 3))
    return np.vstack([field, block])


def test_sparse_tiles_merge_into_aligned_squares_and_dense_ones_stay_nominal():
    """--merge-tile-points: aligned 2x2 and 4x4 squares of nominal tiles that hold at most the limit
    become one tile each; nominal tiles too full for any square stay as before; the cores still partition
    every point, each inside its tile's rectangle, and 0 gives the plan of before."""
    xyz = sparse_beside_dense()
    grid = DensityGrid.covering(xyz.min(0), xyz.max(0), tile_size=50)
    cells, counts = grid.count([xyz])
    plain = plan_tiles(grid, cells, counts, max_points=20_000)
    merged = plan_tiles(grid, cells, counts, max_points=20_000, merge_points=10_000)
    off = plan_tiles(grid, cells, counts, max_points=20_000, merge_points=0)
    assert off.tiles == plain.tiles and np.array_equal(off.cell_tiles, plain.cell_tiles)
    assert len(plain.tiles) == 64
    # the dense block's 4 nominal tiles, the corner square's 3 sparse quarters, the 3 sparse squares
    sides = sorted((t.i1 - t.i0, t.j1 - t.j0) for t in merged.tiles)
    assert sides == [(8, 8)] * 4 + [(16, 16)] * 3 + [(32, 32)] * 3
    assert all(t.count <= 10_000 for t in merged.tiles if t.i1 - t.i0 > 8)
    owner = merged.tile_of(xyz)
    np.testing.assert_array_equal(np.bincount(owner, minlength=len(merged.tiles)), [t.count for t in merged.tiles])
    b = np.array([merged.bounds(t) for t in range(len(merged.tiles))])[owner]
    top = xyz[:, :2].max(axis=0)
    inside = ((xyz[:, 0] >= b[:, 0]) & (xyz[:, 1] >= b[:, 1]) & ((xyz[:, 0] < b[:, 2]) | (xyz[:, 0] == top[0]))
              & ((xyz[:, 1] < b[:, 3]) | (xyz[:, 1] == top[1])))
    assert inside.all()


def test_a_square_over_the_merge_limit_merges_its_quarters_instead():
    """A 4x4 square over the limit is not merged whole: each 2x2 quarter within it is, in quadtree order."""
    xyz = sparse_beside_dense()
    grid = DensityGrid.covering(xyz.min(0), xyz.max(0), tile_size=50)
    merged = plan_tiles(grid, *grid.count([xyz]), max_points=20_000, merge_points=3_000)
    far = [t for t in merged.tiles if t.i0 >= 32 or t.j0 >= 32]  # the three all-sparse 4x4 squares
    assert len(far) == 12 and all(t.i1 - t.i0 == 16 and t.j1 - t.j0 == 16 for t in far)
    assert all(700 <= t.count <= 1_300 for t in far)
    first = far[:4]  # the first square's quarters, in quadtree order
    assert [(t.i0, t.j0) for t in first] == [(0, 32), (0, 48), (16, 32), (16, 48)]


@pytest.mark.parametrize("kind", ["quartered", "crowded", "merged"])
def test_a_tiles_core_mask_is_its_share_of_tile_of(kind):
    """core_mask tests a tile of whole cells against its rectangle instead of looking each cell up: on
    quartered, crowded (split cells beside whole ones) and merged plans, with points on cell edges and on
    the far edges of the extent, it must give exactly tile_of(xyz) == tile."""
    rng = np.random.default_rng(7)
    if kind == "crowded":
        xyz = np.vstack([rng.uniform([0, 0, 0], [100, 100, 5], (20_000, 3)),
                         rng.normal([40.2, 60.2, 1], [0.2, 0.2, 0.5], (20_000, 3))])
    else:
        xyz = clustered_points(60_000) if kind == "quartered" else sparse_beside_dense()
    grid = DensityGrid.covering(xyz.min(0), xyz.max(0), tile_size=25 if kind != "merged" else 50)
    edges = np.array([[grid.origin[0] + k * grid.cell, grid.origin[1] + (k % 7) * grid.cell, 0] for k in range(40)])
    xyz = np.vstack([xyz, edges, [xyz.max(0), xyz.min(0)]])
    cells, counts = grid.count([xyz])
    if kind == "crowded":
        plan = plan_tiles(grid, cells, counts, 2_000, grid.sub_count(xyz, crowded_cells(cells, counts, 2_000)))
        assert any(t.sub is not None for t in plan.tiles) and any(t.sub is None for t in plan.tiles)
    else:
        plan = plan_tiles(grid, cells, counts, 2_000 if kind == "quartered" else 20_000,
                          merge_points=10_000 if kind == "merged" else 0)
    owner = plan.tile_of(xyz)
    for tile in range(len(plan.tiles)):
        np.testing.assert_array_equal(plan.core_mask(tile, xyz), owner == tile)
