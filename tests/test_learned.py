"""The shipped weights behind the simplifier interface, alone and inside `pipeline run`."""
from __future__ import annotations

import laspy
import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

import pipeline
from model import Tile, get_simplifier
from model.learned import load_model
from model.learning import PAPER_WEIGHTS
from tests.conftest import shared_file


def street_tile(n: int = 6_000, seed: int = 1) -> Tile:
    """A facade with a balcony slab above a kerbed road: planes, edges and a step."""
    rng = np.random.default_rng(seed)
    road = np.column_stack([rng.uniform(0, 20, n // 2), rng.uniform(0, 8, n // 2), np.zeros(n // 2)])
    road[road[:, 1] > 6, 2] = 0.15  # kerb and sidewalk
    wall = np.column_stack([rng.uniform(0, 20, n // 3), np.full(n // 3, 8.0), rng.uniform(0, 10, n // 3)])
    rest = n - len(road) - len(wall)
    slab = np.column_stack([rng.uniform(5, 10, rest), rng.uniform(6.5, 8, rest), np.full(rest, 4.0)])
    xyz = np.vstack([road, wall, slab]) + rng.normal(scale=0.005, size=(n, 3))
    core = xyz[:, 0] < 18
    return Tile(xyz - xyz.mean(0), core, np.zeros(3), seed=5)


def test_weights_ship_with_their_record():
    assert PAPER_WEIGHTS.is_file() and PAPER_WEIGHTS.stat().st_size < 1_000_000
    record = torch.load(PAPER_WEIGHTS, map_location="cpu", weights_only=False)["record"]
    assert len(record["train"]) == 64 and len(record["test"]) == 16
    assert not set(record["train"]) & set(record["test"])
    assert record["history"][-1]["loss"] < record["history"][0]["loss"]
    assert not load_model().training


def test_exact_budget_deterministic_and_close_to_the_source():
    tile = street_tile()
    learned = get_simplifier("paper")
    first = learned(tile, 500)
    assert len(first.indices) == 500 == len(np.unique(first.indices))
    assert tile.core[first.indices].all()
    again = learned(tile, 500)
    np.testing.assert_array_equal(first.indices, again.indices)
    np.testing.assert_array_equal(first.xyz, again.xyz)
    coarse = learned(tile, 100)
    np.testing.assert_array_equal(coarse.indices, first.indices[:100])  # a prefix is the coarser result
    np.testing.assert_array_equal(first.xyz, tile.xyz[first.indices])  # picks keep their measured positions


def test_refined_moves_the_same_picks_a_little():
    tile = street_tile()
    picks = get_simplifier("paper")(tile, 500)
    refined = get_simplifier("paper-refined")(tile, 500)
    np.testing.assert_array_equal(refined.indices, picks.indices)
    moved = np.linalg.norm(refined.xyz - tile.xyz[refined.indices], axis=1)
    spacing = cKDTree(tile.xyz).query(tile.xyz, 2)[0][:, 1].mean()
    assert np.median(moved) > 0 and np.median(moved) < 5 * spacing  # refinement nudges, it does not relocate


def record_bytes(points: np.ndarray, skip: int = 0) -> np.ndarray:
    """Each point record as one opaque value, without its first `skip` bytes."""
    return np.ascontiguousarray(points).view(np.uint8).reshape(len(points), -1)[:, skip:].copy().view(
        np.dtype((np.void, points.dtype.itemsize - skip))).ravel()


@pytest.mark.parametrize("method", ["paper", "paper-refined"])
def test_pipeline_run_learned_keeps_every_attribute(tmp_path, method):
    source_path = shared_file("autzen_trim.las")
    out = tmp_path / "learned.las"
    # 60-ft tiles (autzen is in feet), never merged for the paper's network (Method.sees_tile_extent): it sees a
    # tile in its unit ball, so how far refinement moves a point grows with the tile
    pipeline.run(source_path, out, ratio=0.05, method=method, workers=2, tile_size=18.288)
    source, result = laspy.read(source_path), laspy.read(out)
    assert len(result.points) == int(np.floor(0.05 * len(source.points) + 0.5))
    # X, Y, Z are the first 12 bytes of every point format: unmoved picks are whole source records,
    # refined ones keep everything after X, Y, Z from a source point
    skip = 0 if method == "paper" else 12
    kept = record_bytes(result.points.array, skip)
    assert np.isin(kept, record_bytes(source.points.array, skip)).all()
    assert len(np.unique(kept)) == len(kept)
    distance, _ = cKDTree(np.column_stack([source.x, source.y, source.z])).query(
        np.column_stack([result.x, result.y, result.z]))
    assert np.median(distance) < 1.0


def test_exact_latent_fps_mode_keeps_the_contract():
    from model.learned import learned_simplify

    tile = street_tile(2_000)
    first = learned_simplify(tile, 150, exact=True)
    assert len(np.unique(first.indices)) == 150 and tile.core[first.indices].all()
    np.testing.assert_array_equal(learned_simplify(tile, 40, exact=True).indices, first.indices[:40])


def test_refined_points_stay_in_the_box_their_tile_s_picks_span(tmp_path):
    """The refinement moves points in a unit ball scaled by the tile's largest side: points of a flat roof left
    its plane (z 4.4-6.3 m for a plane at 5 m), a 10 m x 10 m mast 300 m tall spread 10 times wider than it
    is, and a point pushed past the grid's int32 reach wrapped to the far side of the scan. Written positions
    stay within the box of the tile's measured picks."""
    rng = np.random.default_rng(2)
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales, header.offsets = [0.001] * 3, [0.0] * 3
    for name, xyz in (("roof", np.column_stack([rng.uniform(0, 10, (3_000, 2)), np.full(3_000, 40.0)])),
                      ("mast", rng.uniform(0, 1, (3_000, 3)) * [10, 10, 300])):
        las = laspy.LasData(header)
        las.x, las.y, las.z = xyz.T
        las.write(tmp_path / f"{name}.las")
        pipeline.run(tmp_path / f"{name}.las", tmp_path / f"{name}-out.las", ratio=0.2, method="paper-refined",
                     workers=1)
        out, source = laspy.read(tmp_path / f"{name}-out.las"), laspy.read(tmp_path / f"{name}.las")
        for axis in "XYZ":  # on the grid
            assert source[axis].min() <= np.min(out[axis]) and np.max(out[axis]) <= source[axis].max(), (name, axis)
    kept = {tuple(row) for row in np.column_stack([source.X, source.Y, source.Z]).tolist()}
    assert sum(tuple(row) not in kept for row in np.column_stack([out.X, out.Y, out.Z]).tolist()) > 300  # moved


def test_weights_are_saved_together_or_not_at_all(tmp_path):
    """A stop while train-detail saved (it wrote in place) left a truncated .pt beside the old .npz: now every
    file of a save is written aside and renamed once all are written; a failure leaves the old ones."""
    from model.learning.saving import saved_together

    pt, npz = tmp_path / "w.pt", tmp_path / "w.npz"
    pt.write_bytes(b"old pt")
    npz.write_bytes(b"old npz")

    def stopped(path):
        path.write_bytes(b"half")
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        saved_together([(pt, lambda path: path.write_bytes(b"new pt")), (npz, stopped)])
    assert pt.read_bytes() == b"old pt" and npz.read_bytes() == b"old npz" and sorted(tmp_path.iterdir()) == [npz, pt]
    saved_together([(pt, lambda path: path.write_bytes(b"new pt")), (npz, lambda path: path.write_bytes(b"new"))])
    assert pt.read_bytes() == b"new pt" and npz.read_bytes() == b"new"
