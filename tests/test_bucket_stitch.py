"""Out-of-core bucketing (core partition, halos) and the seam pass (exact counts, no close pairs)."""
import numpy as np
import pytest
from scipy.spatial import cKDTree

import tiling.store as store_module
from tiling.bucket import (bucket_by_cell, bucket_by_sub_cell, cell_boxes, cells_within, halo_slices, row_ranges,
                           without_cells)
from tiling.plan import SUB_CELLS, DensityGrid, crowded_cells, plan_tiles, summed_cells
from tiling.stitch import SeamBand, band_mask, first_accepted, resolve_seams
from tiling.store import Slice, TileStore

RECORD = np.dtype([("X", "<i4"), ("Y", "<i4"), ("Z", "<i4"), ("intensity", "<u2")])


def scan_pieces(n: int, size: int, seed: int = 0, standpoint: int = 0):
    """n points over 100 x 60 m (the last `standpoint` of them within 1 m of (40.3, 20.3)), as LAS-like
    records of mm integers; pieces of `size` points: (first global index, records, xyz)."""
    rng = np.random.default_rng(seed)
    xyz = rng.uniform([0, 0, 0], [100, 60, 5], size=(n, 3))
    xyz[n - standpoint:] = rng.normal([40.3, 20.3, 1], [0.3, 0.3, 1], size=(standpoint, 3))
    records = np.zeros(n, RECORD)
    for axis, name in enumerate("XYZ"):
        records[name] = np.rint(xyz[:, axis] * 1000)
    records["intensity"] = np.arange(n) % 65536
    xyz = np.column_stack([records[a] for a in "XYZ"]) / 1000.0
    return [(start, records[start:start + size], xyz[start:start + size]) for start in range(0, n, size)], xyz


@pytest.mark.parametrize("standpoint", [0, 12_000])
def test_bucketed_pieces_give_every_tile_its_core_and_full_halo(tmp_path, standpoint):
    """Pieces stored by cell (and, for cells the plan splits, copied by sub-cell): every tile's slices
    hold its whole core and halo, records intact; a tile in a split cell reads its own sub-cells, not
    the whole cell."""
    pieces, xyz = scan_pieces(30_000 + standpoint, 7_000, standpoint=standpoint)
    grid = DensityGrid.covering(xyz.min(0), xyz.max(0), tile_size=20)
    store = TileStore.create(tmp_path / "tiles", RECORD, {})
    index = []
    cell_parts, count_parts = [], []
    for number, (first, records, points) in enumerate(pieces):
        buckets = bucket_by_cell(records, points, first, grid)
        store.write_piece(number, buckets.rows)
        cell_parts.append(buckets.cells)
        count_parts.append(buckets.counts)
        index.append(buckets)
    cells, counts = summed_cells(cell_parts, count_parts)
    crowded = crowded_cells(cells, counts, 1_500)
    copies = {}
    for number, (first, records, points) in enumerate(pieces):
        inside = np.isin(grid.cell_of(points), crowded)
        rows, copies[number] = bucket_by_sub_cell(records[inside], first + np.flatnonzero(inside), points[inside],
                                                  np.zeros(inside.sum(), bool), grid, crowded)
        store.write_piece(number, rows, crowded=True)
    plan = plan_tiles(grid, cells, counts, 1_500, sum(c.counts for c in copies.values()) if len(crowded) else None)
    assert counts.sum() == len(xyz) and sum(t.count for t in plan.tiles) == len(xyz)
    assert all(t.count <= 1_500 for t in plan.tiles) and (len(plan.split_cells) > 0) == (standpoint > 0)
    reopened = TileStore.open(tmp_path / "tiles")
    seen_core = np.zeros(len(xyz), dtype=int)
    overlap = 1.5
    in_split = np.isin(grid.cell_of(xyz), plan.split_cells)
    if standpoint:  # each split cell's mean spacing: the square root of its occupied sub-cells' area per point
        si, sj = grid.sub_cell_of(xyz[in_split])
        occupied = {(c, a, b) for c, a, b in zip(grid.cell_of(xyz[in_split]).tolist(), si.tolist(), sj.tolist())}
        spacing = {c: np.sqrt(sum(1 for o in occupied if o[0] == c) * (grid.cell / SUB_CELLS) ** 2
                              / counts[cells == c][0]) for c in plan.split_cells.tolist()}
        split_reach = np.array([64 * spacing.get(c, 0.0) for c in grid.cell_of(xyz).tolist()])
        assert 0 < split_reach.max() < overlap  # the standpoint's halo is narrower than the others'
    else:
        split_reach = np.zeros(len(xyz))
    for tile_id, tile in enumerate(plan.tiles):
        slices = [s for number, b in enumerate(index)
                  for s in halo_slices(plan, tile_id, overlap, number, b.cells, b.starts,
                                       copies[number] if len(crowded) else None)]
        for cache in (0, 10**8):
            stored = reopened.load(slices, cache)
            # records survive byte for byte and match their global index
            assert (stored.records["intensity"] == stored.index % 65536).all()
        assert len(np.unique(stored.index)) == len(stored.index)  # no row read twice
        p = xyz[stored.index]
        np.testing.assert_array_equal(np.column_stack([stored.records[a] for a in "XYZ"]) / 1000.0, p)
        core = plan.core_mask(tile_id, p)
        seen = plan.halo_mask(core, tile_id, p, overlap)
        assert core.sum() == tile.count
        seen_core[stored.index[core]] += 1
        x0, y0, x1, y1 = plan.bounds(tile_id)
        reach = np.where(in_split, np.minimum(overlap, split_reach), overlap)  # a split cell is seen less deep
        near = (xyz[:, 0] >= x0 - reach) & (xyz[:, 0] < x1 + reach) & (xyz[:, 1] >= y0 - reach) \
            & (xyz[:, 1] < y1 + reach)
        assert set(np.flatnonzero(near)) == set(stored.index[seen].tolist())  # the whole halo, nothing more
        wider = reach + 3 * grid.cell / SUB_CELLS  # of split cells, only the sub-cells the halo meets are read
        near_wider = (xyz[:, 0] >= x0 - wider) & (xyz[:, 0] < x1 + wider) & (xyz[:, 1] >= y0 - wider) \
            & (xyz[:, 1] < y1 + wider) & in_split
        assert sum(s.stop - s.start for s in slices if s.crowded) <= near_wider.sum()

        def in_halo(part):
            return plan.halo_mask(plan.core_mask(tile_id, xyz[part.index]), tile_id, xyz[part.index], overlap)

        filtered = reopened.load(slices, 0, keep=in_halo)  # chunk by chunk: the same points, in the same order
        np.testing.assert_array_equal(filtered.index, stored.index[seen])
        np.testing.assert_array_equal(filtered.records, stored.records[seen])
    assert (seen_core == 1).all()


def test_chunk_cache_returns_the_same_rows_within_its_budget(tmp_path, monkeypatch):
    monkeypatch.setattr(store_module, "ROW_CHUNK", 1_000)  # slices then span several chunks
    monkeypatch.setattr(store_module, "CHUNKS", store_module.ChunkCache())
    store = TileStore.create(tmp_path / "tiles", RECORD, {})
    pieces, _ = scan_pieces(12_000, 6_000)
    for number, (first, records, _) in enumerate(pieces):
        store.write_piece(number, store_module.encode_rows(records, np.arange(first, first + len(records))))
    rng = np.random.default_rng(3)
    starts = rng.integers(0, 6_000, 20)
    slices = [Slice(int(i % 2), int(a), int(min(a + rng.integers(0, 2_500), 6_000))) for i, a in enumerate(starts)]
    row_bytes = RECORD.itemsize + store_module.TAIL
    budget = 4_000 * row_bytes  # four chunks: the most a slice of under 2,500 rows spans
    cached, direct = store.load(slices, budget), store.load(slices, 0)
    np.testing.assert_array_equal(cached.index, direct.index)
    np.testing.assert_array_equal(cached.index, np.concatenate([np.arange(s.start, s.stop) + 6_000 * s.piece
                                                                for s in slices]))
    assert store_module.CHUNKS._bytes <= budget
    reads = store_module.CHUNKS.reads
    store.load(slices[-1:], budget)
    assert store_module.CHUNKS.reads == reads  # the last slice's chunks are still cached


def test_split_cells_are_cut_out_of_cell_ranges():
    """A halo's cell ranges lose the split cells (read from their sorted copy instead): at a range's
    start, middle and end, in a one-cell range, and in adjacent ranges; cells outside stay untouched."""
    ranges = np.array([[0, 10], [10, 20], [40, 41]])
    split = np.array([0, 5, 9, 10, 40, 50])
    assert without_cells(ranges, split).tolist() == [[1, 5], [6, 9], [11, 20]]
    assert without_cells(ranges, np.array([30, 60])).tolist() == ranges.tolist()
    assert cells_within(split, ranges).tolist() == [0, 1, 2, 3, 4]
    kept = {c for lo, hi in without_cells(ranges, split).tolist() for c in range(lo, hi)}
    assert kept == {c for lo, hi in ranges.tolist() for c in range(lo, hi)} - set(split.tolist())


def test_row_ranges_merge_adjacent_and_skip_empty():
    cells = np.array([2, 3, 7, 9])
    starts = np.array([0, 5, 6, 10, 12])
    ranges = row_ranges(cells, starts, np.array([[0, 2], [2, 4], [4, 8], [8, 9], [9, 20]]))
    np.testing.assert_array_equal(ranges, [[0, 12]])
    np.testing.assert_array_equal(row_ranges(cells, starts, np.array([[2, 3], [7, 8]])), [[0, 5], [6, 10]])
    assert row_ranges(cells, starts, np.array([[4, 7]])).shape == (0, 2)


def test_first_accepted_skips_rejected_and_fills_in_when_short():
    np.testing.assert_array_equal(first_accepted(10, 4, np.array([1, 2])), [0, 3, 4, 5])
    np.testing.assert_array_equal(first_accepted(5, 4, np.array([0, 1, 2])), [0, 1, 3, 4])


def test_seam_pass_removes_cross_tile_pairs_and_keeps_counts():
    rng = np.random.default_rng(4)
    rects = [(0.0, 0.0, 10.0, 10.0), (10.0, 0.0, 20.0, 10.0)]
    candidates = []
    for x0, y0, x1, y1 in rects:
        pts = np.column_stack([rng.uniform(x0, x1, 400), rng.uniform(y0, y1, 400), np.zeros(400)])
        candidates.append(pts)
    # plant near-duplicates straddling the seam at x = 10
    seam = np.column_stack([np.full(30, 9.999), np.linspace(0.5, 9.5, 30), np.zeros(30)])
    candidates[0][:30] = seam
    candidates[1][:30] = seam + [0.0015, 0, 0]
    budgets = np.array([350, 350])
    tolerance = 0.01
    bands = []
    for tile_id, (pts, rect) in enumerate(zip(candidates, rects)):
        near = np.flatnonzero(band_mask(pts, rect, tolerance))
        bands.append(SeamBand(tile_id, near, pts[near]))
    rejections = resolve_seams(bands, np.array([400, 400]), budgets, tolerance)
    kept = [pts[first_accepted(len(pts), b, rejections.get(t, np.empty(0, int)))]
            for t, (pts, b) in enumerate(zip(candidates, budgets))]
    assert [len(k) for k in kept] == [350, 350]
    assert len(rejections[1]) == 30 and 0 not in rejections
    distances, _ = cKDTree(kept[0]).query(kept[1])
    assert distances.min() >= tolerance


def test_the_seam_pass_pairs_a_tiles_duplicates_as_one_and_rejects_as_point_pairs_would():
    """Thousands of returns at one spot in one tile (a sensor's origin, a duplicated export) once made the
    seam pass list every pair among them (20k: 4 minutes). Grouped by tile and position, the rejections are
    those of the rule applied point by point (brute force below), duplicates on both sides of a seam included,
    and 20,000 duplicates resolve at once."""
    rng = np.random.default_rng(6)
    tolerance, spot = 0.01, np.array([9.999, 5.0, 0.0])
    tiles = []
    for tile_id, x0 in enumerate((0.0, 10.0, 20.0)):
        xyz = np.column_stack([rng.uniform(x0, x0 + 10, 300), rng.uniform(0, 10, 300), np.zeros(300)])
        tiles.append(xyz)
    tiles[0] = np.concatenate([tiles[0], np.repeat(spot[None], 20_000, axis=0)])  # candidates ranked last
    tiles[1][:50] = spot + [0.002, 0.0, 0.0]  # duplicates across the seam, ranked first
    tiles[1][50:60] = [10.0, 7.0, 0.0]
    tiles[0][:10] = [9.995, 7.0, 0.0]
    budgets, counts = np.array([310, 250, 250]), np.array([len(t) for t in tiles])
    bands = [SeamBand(tile_id, np.arange(len(xyz)), xyz) for tile_id, xyz in enumerate(tiles)]
    rejections = resolve_seams(bands, counts, budgets, tolerance)
    accepted: list[np.ndarray] = []
    for tile_id, xyz in enumerate(tiles):  # the rule point by point: a candidate near an accepted earlier one
        earlier = np.concatenate(accepted) if accepted else np.empty((0, 3))
        near = (cKDTree(earlier).query(xyz)[0] <= tolerance) if len(earlier) else np.zeros(len(xyz), dtype=bool)
        np.testing.assert_array_equal(rejections.get(tile_id, np.empty(0, int)), np.flatnonzero(near))
        accepted.append(xyz[first_accepted(len(xyz), int(budgets[tile_id]), np.flatnonzero(near))])
    assert len(rejections[1]) == 60 and 0 not in rejections


def test_a_store_made_again_is_empty_and_a_cut_piece_is_an_error_not_short_rows(tmp_path):
    """A new run's store at a leftover path starts empty; a piece file cut short (a damaged scratch disk)
    fails the read with its name, and never yields fewer rows than the slice asked for."""
    pieces, _ = scan_pieces(3_000, 3_000)
    first, records, _ = pieces[0]
    rows = store_module.encode_rows(records, np.arange(first, first + len(records)))
    TileStore.create(tmp_path / "tiles", RECORD, {"scales": [0.001] * 3}).write_piece(0, rows)
    store = TileStore.open(tmp_path / "tiles")
    assert store.attrs == {"scales": [0.001] * 3} and store.record_dtype == RECORD
    np.testing.assert_array_equal(store.load([Slice(0, 100, 2_000)]).records, records[100:2_000])
    piece = tmp_path / "tiles" / store_module.array_name(0)
    piece.write_bytes(piece.read_bytes()[:-1])
    with pytest.raises(OSError, match="p0.rows.*ends first"):
        store.load([Slice(0, 100, 3_000)])
    TileStore.create(tmp_path / "tiles", RECORD, {})
    assert not piece.exists() and TileStore.exists(tmp_path / "tiles")


def point_by_point_rejections(tiles: list[np.ndarray], budgets: np.ndarray, tolerance: float) -> list[np.ndarray]:
    """The seam rule by brute force: each tile in turn rejects its candidates within `tolerance` of a point an
    earlier tile accepted (scipy's ball query: a point exactly at the tolerance is within it)."""
    accepted: list[np.ndarray] = []
    rejected = []
    for tile_id, xyz in enumerate(tiles):
        earlier = np.concatenate(accepted) if accepted else np.empty((0, 3))
        near = np.zeros(len(xyz), dtype=bool)
        if len(earlier):
            near = np.array([len(hits) > 0 for hits in cKDTree(earlier).query_ball_point(xyz, tolerance)], dtype=bool)
        rejected.append(np.flatnonzero(near))
        accepted.append(xyz[first_accepted(len(xyz), int(budgets[tile_id]), rejected[-1])])
    return rejected


@pytest.mark.parametrize("seed", range(8))
def test_seam_rejections_are_the_point_by_point_rule_with_ties_at_the_tolerance(seed):
    """Coordinates on a LAS-like grid put many points exactly one tolerance apart (and duplicates many deep):
    each pair is in or out as scipy's ball query decides, so seams keep the same points; three tiles, the
    last reaching both others."""
    rng = np.random.default_rng(seed)
    scale, origin, tolerance = [(0.01, 687_000.0, 0.01), (0.001, 4_810_000.0, 0.003), (0.125, 1024.0, 0.25),
                                (0.00025, 120.0, 0.0305)][seed % 4]  # 0.125 m steps: exact distances
    steps = rng.integers(0, round(0.4 / scale) if scale < 0.1 else 16, size=(3000, 3))
    steps = np.concatenate([steps, np.repeat(steps[:5], 40, axis=0)])
    xyz = origin + steps * scale
    tiles = [xyz[:1_000], xyz[1_000:2_000], xyz[2_000:]]
    budgets = np.array([900, 900, 1_100])
    rejections = resolve_seams([SeamBand(t, np.arange(len(p)), p) for t, p in enumerate(tiles)],
                               np.array([len(p) for p in tiles]), budgets, tolerance)
    expected = point_by_point_rejections(tiles, budgets, tolerance)
    assert sum(len(r) for r in expected) > 100
    for tile_id, rejected in enumerate(expected):
        np.testing.assert_array_equal(rejections.get(tile_id, np.empty(0, int)), rejected)


def test_a_dense_blob_on_a_seam_is_resolved_by_the_point_by_point_rule():
    """A 3 mm blob of 6,000 returns on a tile corner (distinct points, a jittered no-return spot): every pair of
    it lies within the tolerance, and listing them took 261 s for 100,000; the rule still holds."""
    rng = np.random.default_rng(9)
    blob = np.array([10.0, 10.0, 2.0]) + rng.normal(0, 0.003, size=(6_000, 3))
    tiles = [np.concatenate([blob[i::4], np.column_stack([rng.uniform(0, 10, (200, 2)), np.zeros(200)])])
             for i in range(4)]
    budgets = np.array([800, 800, 800, 800])
    rejections = resolve_seams([SeamBand(t, np.arange(len(p)), p) for t, p in enumerate(tiles)],
                               np.array([len(p) for p in tiles]), budgets, 0.01)
    expected = point_by_point_rejections(tiles, budgets, 0.01)
    assert len(expected[1]) > 1_000
    for tile_id, rejected in enumerate(expected):
        np.testing.assert_array_equal(rejections.get(tile_id, np.empty(0, int)), rejected)


def test_a_halo_that_misses_a_pieces_box_has_no_rows_in_it():
    """The runner asks only the pieces whose cell boxes a halo meets: every other piece gives no rows."""
    rng = np.random.default_rng(4)
    grid = DensityGrid((0.0, 0.0), 1.0, (200, 150))
    pieces = []
    for k in range(12):  # strips of a drive: each piece in its own stretch of the grid
        xy = np.column_stack([rng.uniform(15 * k, 15 * k + 25, 500), rng.uniform(0, 40 + 8 * k, 500)])
        cells = np.unique(grid.cell_of(xy))
        pieces.append((cells, np.arange(len(cells) + 1) * 3))
    boxes = cell_boxes([cells for cells, _ in pieces] + [np.empty(0, dtype=np.int64)], grid.shape[1])
    assert (boxes[-1] == 0).all()
    plan = plan_tiles(grid, *summed_cells([c for c, _ in pieces], [np.diff(s) for _, s in pieces]), 400)
    asked = found = 0
    for tile_id in range(len(plan.tiles)):
        i0, i1, j0, j1 = plan.halo_cell_rect(tile_id, 2.0)
        ranges = plan.halo_cell_ranges(tile_id, 2.0)
        for k, (cells, starts) in enumerate(pieces):
            meets = boxes[k, 0] < i1 and boxes[k, 1] > i0 and boxes[k, 2] < j1 and boxes[k, 3] > j0
            has_rows = len(row_ranges(cells, starts, ranges)) > 0
            assert meets or not has_rows
            asked, found = asked + meets, found + has_rows
    assert found <= asked < len(plan.tiles) * len(pieces) / 2  # most pairs are skipped


def test_stable_order_is_numpys_stable_argsort_for_narrow_and_wide_keys():
    """The piece sort takes 16-bit offsets where the keys span fewer than 2**16 values: the same order as a
    stable argsort of the keys themselves, ties in index order, on either side of that span and when empty."""
    from tiling.bucket import stable_order

    rng = np.random.default_rng(4)
    for span in (1, 300, 2**16 - 1, 2**16, 2**40):
        keys = rng.integers(5_000, 5_000 + span, 20_000).astype(np.int64)
        np.testing.assert_array_equal(stable_order(keys), np.argsort(keys, kind="stable"))
    assert len(stable_order(np.empty(0, dtype=np.int64))) == 0


def test_a_tiles_band_given_in_parts_is_one_band():
    """Bands of one tile given separately are joined (resolve_seams' callers may hand a tile's band in pieces):
    the rejections are those of the whole band."""
    rng = np.random.default_rng(10)
    tiles = [np.column_stack([rng.uniform(9.98, 10.0, 400), rng.uniform(0, 1, 400), np.zeros(400)]),
             np.column_stack([rng.uniform(10.0, 10.02, 400), rng.uniform(0, 1, 400), np.zeros(400)])]
    counts, budgets = np.array([400, 400]), np.array([300, 300])
    whole = resolve_seams([SeamBand(t, np.arange(400), p) for t, p in enumerate(tiles)], counts, budgets, 0.01)
    parts = [SeamBand(1, np.arange(200, 400), tiles[1][200:]), SeamBand(0, np.arange(400), tiles[0]),
             SeamBand(1, np.arange(200), tiles[1][:200])]
    split = resolve_seams(parts, counts, budgets, 0.01)
    assert len(whole[1]) > 50 and whole.keys() == split.keys()
    np.testing.assert_array_equal(np.sort(split[1]), whole[1])
