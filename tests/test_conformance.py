"""What a run relies on from every simplifier, checked on every registered method (a new method gets the
whole suite by registering in model.registry): an exact budget of distinct core points, the same picks
for the same tile and seed and for the tile moved, prefixes as good as a coarser selection, the same
picks without the halo for a method that says it never reads it, and tiny or degenerate tiles."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from model.methods import Method
from model.registry import REGISTERED
from model.selection import Tile

METHODS = sorted(REGISTERED)
CENTRE = np.array([500_000.0, 4_000_000.0, 100.0])


@pytest.fixture(scope="module")
def tile() -> Tile:
    """3,000 points of a gently rough 20 x 20 m slab, its middle 16 m the core, centred as a run centres."""
    rng = np.random.default_rng(5)
    xyz = rng.uniform(0, 20, size=(3_000, 3)) * [1, 1, 0.1]
    core = (xyz[:, 0] > 2) & (xyz[:, 0] < 18)
    return Tile(xyz - xyz.mean(axis=0), core, CENTRE, seed=11)


def assert_valid(tile: Tile, method: Method, budget: int) -> np.ndarray:
    """The selection's indices after checking the contract: `budget` distinct core points (fewer only if the
    core is smaller), and their own positions unless the method moves points."""
    selection = method(tile, budget)
    indices = selection.indices
    assert indices.dtype.kind == "i" and len(indices) == min(budget, tile.core_count)
    assert len(np.unique(indices)) == len(indices) and tile.core[indices].all()
    assert selection.xyz.shape == (len(indices), 3) and np.isfinite(selection.xyz).all()
    if method.keeps_positions():
        np.testing.assert_array_equal(selection.xyz, tile.xyz[indices])
    return indices


@pytest.mark.parametrize("name", METHODS)
def test_exact_budget_of_distinct_core_points(name, tile):
    for budget in (0, 1, 37, 600, tile.core_count, tile.core_count + 5):
        assert_valid(tile, REGISTERED[name], budget)


@pytest.mark.parametrize("name", METHODS)
def test_same_tile_and_seed_give_the_same_picks(name, tile):
    method = REGISTERED[name]
    np.testing.assert_array_equal(method(tile, 400).indices, method(tile, 400).indices)


@pytest.mark.parametrize("name", METHODS)
def test_moving_the_tile_keeps_the_picks(name, tile):
    """A tile's points relative to another centre (the same absolute positions) give the same picks."""
    shift = np.array([3.0, -2.0, 1.0])
    moved = Tile(tile.xyz + shift, tile.core, tile.centre - shift, tile.seed)
    method = REGISTERED[name]
    np.testing.assert_array_equal(method(tile, 400).indices, method(moved, 400).indices)


@pytest.mark.parametrize("name", METHODS)
def test_a_prefix_is_as_good_as_a_coarser_selection(name, tile):
    """A run keeps the first `budget` of `budget + reserve` picks, and `--levels` the first picks of each
    tile: the first 60 of 600 cover the core within 1.25x of what 60 picks of their own cover."""
    method = REGISTERED[name]
    core = tile.xyz[tile.core]
    prefix = method(tile, 600).indices[:60]
    coarse = method(tile, 60).indices
    gap = {label: cKDTree(tile.xyz[indices]).query(core)[0].max()
           for label, indices in (("prefix", prefix), ("coarse", coarse))}
    assert gap["prefix"] <= 1.25 * gap["coarse"]


@pytest.mark.parametrize("name", [name for name in METHODS if not REGISTERED[name].reads_halo])
def test_a_method_that_never_reads_the_halo_picks_the_same_without_it(name, tile):
    """A run loads no halo for such a method: the picks must be those it makes with the halo there."""
    core = np.flatnonzero(tile.core)
    alone = Tile(tile.xyz[core], np.ones(len(core), dtype=bool), tile.centre, tile.seed)
    method = REGISTERED[name]
    np.testing.assert_array_equal(core[method(alone, 500).indices], method(tile, 500).indices)


@pytest.mark.parametrize("name", METHODS)
@pytest.mark.parametrize("n", range(1, 9))
def test_tiny_tiles_keep_exactly_their_core(name, n):
    """n points, the last two halo when n > 3: every budget gives distinct core points, and a budget of
    the whole core keeps exactly the core points."""
    xyz = np.random.default_rng(n).uniform(size=(n, 3))
    core = np.arange(n) < (n - 2 if n > 3 else n)
    tile = Tile(xyz, core, CENTRE, seed=2)
    method = REGISTERED[name]
    for budget in range(1, tile.core_count + 1):
        assert_valid(tile, method, budget)
    assert sorted(method(tile, tile.core_count).indices) == np.flatnonzero(core).tolist()


def degenerate_tiles() -> dict[str, Tile]:
    """Tiles a scan can hold: one point repeated, every point twice, points on a line, points on a plane."""
    rng = np.random.default_rng(3)
    spread = rng.uniform(-5, 5, size=(400, 3))
    line = np.outer(np.linspace(-10, 10, 400), [0.6, 0.8, 0.0])
    plane = spread * [1, 1, 0]
    return {name: Tile(xyz, np.ones(len(xyz), dtype=bool), CENTRE, seed=4)
            for name, xyz in (("repeated", np.zeros((300, 3))), ("doubled", np.concatenate([spread, spread])),
                              ("line", line), ("plane", plane))}


@pytest.mark.parametrize("name", METHODS)
@pytest.mark.parametrize("shape", ["repeated", "doubled", "line", "plane"])
def test_degenerate_tiles(name, shape):
    tile = degenerate_tiles()[shape]
    for budget in (1, tile.core_count // 10, tile.core_count // 2, tile.core_count):
        assert_valid(tile, REGISTERED[name], budget)
