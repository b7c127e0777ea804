"""Out-of-core bucketing (core partition, halos) and the seam pass (exact counts, no close pairs)."""
import numpy as np
from scipy.spatial import cKDTree

from tiling.bucket import bucket_points
from tiling.plan import DensityGrid, plan_tiles
from tiling.stitch import SeamBand, band_mask, first_accepted, resolve_seams
from tiling.store import TileStore

RECORD = np.dtype([("X", "<i4"), ("Y", "<i4"), ("Z", "<i4"), ("intensity", "<u2")])


def scan_chunks(n: int, chunk: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    xyz = rng.uniform([0, 0, 0], [100, 60, 5], size=(n, 3))
    records = np.zeros(n, RECORD)
    for axis, name in enumerate("XYZ"):
        records[name] = np.rint(xyz[:, axis] * 1000)
    records["intensity"] = np.arange(n) % 65536
    xyz = np.column_stack([records[a] for a in "XYZ"]) / 1000.0
    return [(records[s:s + chunk], xyz[s:s + chunk]) for s in range(0, n, chunk)], xyz


def test_bucketing_partitions_cores_and_fills_halos(tmp_path):
    chunks, xyz = scan_chunks(30_000, 7_000)
    grid = DensityGrid.covering(xyz.min(0), xyz.max(0), tile_size=20)
    plan = plan_tiles(grid, grid.count([c[1] for c in chunks]), max_points=1_500)
    store = TileStore.create(tmp_path / "t.zarr", RECORD, {})
    core_counts = bucket_points(chunks, plan, overlap=1.5, store=store, buffer_bytes=50_000)
    assert core_counts.sum() == len(xyz)
    seen_core = np.zeros(len(xyz), dtype=int)
    reopened = TileStore.open(tmp_path / "t.zarr")
    for tile_id in range(len(plan.tiles)):
        points = reopened.load(tile_id)
        seen_core[points.index[points.core]] += 1
        assert points.core.sum() == core_counts[tile_id]
        # records survive byte for byte and match their global index
        assert (points.records["intensity"] == points.index % 65536).all()
        x0, y0, x1, y1 = plan.bounds(tile_id)
        p = xyz[points.index]
        in_core = (p[:, 0] >= x0) & (p[:, 0] < x1) & (p[:, 1] >= y0) & (p[:, 1] < y1)
        expected_halo = ((p[:, 0] >= x0 - 1.5) & (p[:, 0] < x1 + 1.5) & (p[:, 1] >= y0 - 1.5) & (p[:, 1] < y1 + 1.5))
        assert expected_halo.all()
        assert (in_core[~points.core] == False).all()  # noqa: E712
        # every point of the scan within the halo band is present
        all_near = ((xyz[:, 0] >= x0 - 1.5) & (xyz[:, 0] < x1 + 1.5) & (xyz[:, 1] >= y0 - 1.5) & (xyz[:, 1] < y1 + 1.5))
        assert set(np.flatnonzero(all_near)) == set(points.index.tolist())
    assert (seen_core == 1).all()


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
