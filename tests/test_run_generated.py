"""End to end on scans made here: seams, determinism across worker counts, PLY ingest."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import laspy
import numpy as np
import pytest
import zarr
from plyfile import PlyData, PlyElement
from scipy.spatial import cKDTree

import pipeline
from model import Tile
from model.baselines import fps_simplify
from pipeline.engine.tasks import TileJob, TileOutcome
from pipeline.engine.threads import available_cores
from tiling.plan import TilePlan


def write_dense_patch(path: Path, n: int = 120_000, seed: int = 0) -> None:
    """A 16 m x 16 m gently curved patch at ~470 points/m^2: spacing well under 5 cm, many tile seams."""
    rng = np.random.default_rng(seed)
    header = laspy.LasHeader(version="1.2", point_format=3)
    header.scales = [0.001] * 3
    header.offsets = [500_000.0, 4_000_000.0, 0.0]
    las = laspy.LasData(header)
    xy = rng.uniform(0, 16, size=(n, 2))
    las.x = 500_000 + xy[:, 0]
    las.y = 4_000_000 + xy[:, 1]
    las.z = 0.2 * np.sin(xy[:, 0]) + 0.01 * rng.normal(size=n)
    las.intensity = rng.integers(0, 4000, n)
    las.gps_time = np.sort(rng.uniform(0, 100, n))
    las.write(path)


def write_flat_scene(path: Path, xy: np.ndarray, noise: float, rng: np.random.Generator) -> laspy.LasData:
    """(n, 2) metres of ground at 500 km E / 4,000 km N, z drawn as Gaussian noise of `noise` m, written as LAS."""
    header = laspy.LasHeader(version="1.2", point_format=3)
    header.scales, header.offsets = [0.001] * 3, [500_000.0, 4_000_000.0, 0.0]
    las = laspy.LasData(header)
    las.x, las.y, las.z = 500_000 + xy[:, 0], 4_000_000 + xy[:, 1], noise * rng.normal(size=len(xy))
    las.write(path)
    return las


def cross_tile_close_pairs(store: Path, tolerance: float) -> int:
    """Pairs of output points from different tiles closer than tolerance (tiles from the zarr tile index)."""
    group = zarr.open_group(str(store), mode="r")
    xyz = np.column_stack([group[a][:] for a in "xyz"])
    tile = np.empty(len(xyz), dtype=np.int64)
    for tile_id, start, count in zip(group["tile"][:], group["tile_start"][:], group["tile_count"][:]):
        tile[start:start + count] = tile_id
    pairs = cKDTree(xyz).query_pairs(tolerance, output_type="ndarray")
    return int((tile[pairs[:, 0]] != tile[pairs[:, 1]]).sum())


@pytest.fixture(scope="module")
def dense_patch(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("patch") / "patch.las"
    write_dense_patch(path)
    return path


@pytest.mark.parametrize("method", ["random", "fps"])
def test_no_near_duplicates_across_seams(tmp_path, dense_patch, method):
    settings = dict(ratio=0.5, method=method, tile_size=4.0, overlap=0.5, workers=1)
    loose = pipeline.run(dense_patch, tmp_path / "loose.zarr", seam_tolerance=0.0, **settings)
    strict = pipeline.run(dense_patch, tmp_path / "strict.zarr", seam_tolerance=0.03, **settings)
    assert loose.output_points == strict.output_points == 60_000
    assert cross_tile_close_pairs(tmp_path / "loose.zarr", 0.03) > 0  # the data really has seam conflicts
    assert cross_tile_close_pairs(tmp_path / "strict.zarr", 0.03) == 0


def untiled_fps_gap(xyz: np.ndarray, count: int) -> float:
    """Largest distance from a point to the nearest of `count` FPS picks over the whole cloud at once."""
    from model import Tile, get_simplifier

    tile = Tile(xyz - xyz.mean(0), np.ones(len(xyz), dtype=bool), np.zeros(3), seed=0)
    kept = get_simplifier("fps")(tile, count).indices
    return float(cKDTree(xyz[kept]).query(xyz)[0].max())


def test_tiled_fps_covers_as_one_pass_would(tmp_path, dense_patch):
    """Sixteen 4 m tiles: no hole along their seams, so the largest gap stays near one FPS over the patch."""
    pipeline.run(dense_patch, tmp_path / "fps.las", ratio=0.05, method="fps", tile_size=4.0, workers=1)
    scan, out = laspy.read(dense_patch), laspy.read(tmp_path / "fps.las")
    xyz = np.column_stack([scan.x, scan.y, scan.z]) - [500_000, 4_000_000, 0]
    kept = np.column_stack([out.x, out.y, out.z]) - [500_000, 4_000_000, 0]
    gap = cKDTree(kept).query(xyz)[0].max()
    assert gap <= 1.3 * untiled_fps_gap(xyz, len(kept))


def test_a_tile_far_larger_than_the_scan_still_finds_its_spacing(tmp_path):
    """The survey's voxel sizes centre on a spacing guessed from occupied grid cells, which a 5 km tile makes
    far too coarse for a 20 m scene (one 625 m cell): the sizes reach 2**8 either side of the guess, so the
    even spacing (the floor of the cover radius) is still found, not held at the finest size, a radius too
    coarse for the sparse part (largest gap 0.83 m as one tile against 0.26 m tiled, before)."""
    rng = np.random.default_rng(3)
    xy = np.concatenate([rng.uniform(0, 5, size=(20_000, 2)), rng.uniform(0, 20, size=(2_000, 2))])  # dense corner
    scene = tmp_path / "scene.las"
    las = write_flat_scene(scene, xy, 0.05, rng)
    scanned = np.column_stack([las.x, las.y, las.z])

    def largest_gap(out: Path) -> float:
        kept = laspy.read(out)
        return float(cKDTree(np.column_stack([kept.x, kept.y, kept.z])).query(scanned)[0].max())

    tiled, whole = tmp_path / "tiled.laz", tmp_path / "whole.laz"
    pipeline.run(scene, tiled, ratio=0.1, method="stratified", tile_size=4.0, merge_tile_points=0)
    pipeline.run(scene, whole, ratio=0.1, method="stratified", tile_size=5000.0, max_tile_points=1_000_000)
    assert largest_gap(whole) <= 1.2 * largest_gap(tiled)


def test_fps_budgets_follow_area_not_point_count(tmp_path):
    """Left half ten times denser than the right: tiled FPS keeps about as many points per m^2 on both
    halves, as one pass would (budgets in proportion to counts would keep ten times more on the left)."""
    rng = np.random.default_rng(3)
    xy = np.concatenate([rng.uniform([0, 0], [8, 16], size=(50_000, 2)), rng.uniform([8, 0], [16, 16], size=(5_000, 2))])
    write_flat_scene(tmp_path / "two.las", xy, 0.01, rng)
    pipeline.run(tmp_path / "two.las", tmp_path / "fps.las", ratio=0.04, method="fps", tile_size=4.0, workers=1)
    kept_x = laspy.read(tmp_path / "fps.las").x - 500_000
    left, right = (kept_x < 8).sum(), (kept_x >= 8).sum()
    assert left + right == 2_200 and 0.75 < left / right < 1.33


def test_a_tile_with_holes_fills_its_dense_part_at_the_scans_rate(tmp_path):
    """Two 8 m tiles, both dense over most of their area, the right one also holding a sparse strip: the
    right tile's budget is its fill share plus its holes, so its dense part keeps the share the left
    tile's does: one fill rate across the scan, as one pass would have. (With a floor of a point per voxel
    of the hole radius instead, the right tile paid for its holes from its own fill: 0.84x the left's
    share, a step in density at the seam.)"""
    rng = np.random.default_rng(5)
    dense = rng.uniform([0, 0], [12, 8], size=(96_000, 2))
    sparse = rng.uniform([12, 0], [16, 8], size=(1_200, 2))
    xy = np.concatenate([dense, sparse])
    scene = tmp_path / "scene.las"
    write_flat_scene(scene, xy, 0.01, rng)
    pipeline.run(scene, tmp_path / "out.las", ratio=0.1, method="stratified", tile_size=8.0, merge_tile_points=0,
                 workers=1)
    kept_x = laspy.read(tmp_path / "out.las").x - 500_000

    def share(low: float, high: float) -> float:
        return ((kept_x >= low) & (kept_x < high)).sum() / (0.1 * ((xy[:, 0] >= low) & (xy[:, 0] < high)).sum())

    assert share(12, 16) > 1.5  # the sparse strip's holes are covered
    assert 0.9 < share(8, 12) / share(0, 8) < 1.1


@pytest.mark.parametrize("method", ["fps", "learned"])
def test_one_and_two_workers_and_this_process_give_identical_bytes(tmp_path, dense_patch, method):
    """The patch (120k points) runs in this process by default; on 1 or 2 Dask workers it must come out the
    same, byte for byte (the in-process run holds BLAS and torch to one thread, as a worker does)."""
    outputs = []
    for name, settings in (("here", {}), ("w1", dict(workers=1, in_process_points=0)),
                           ("w2", dict(workers=2, in_process_points=0))):
        out = tmp_path / f"{name}.laz"
        pipeline.run(dense_patch, out, ratio=0.1, method=method, tile_size=4.0, seed=7, **settings)
        outputs.append(out.read_bytes())
    assert outputs[0] == outputs[1] == outputs[2]


@pytest.mark.skipif(available_cores() < 2, reason="one core: a run has one task thread and picks on it")
@pytest.mark.parametrize("method", ["fps", "voxel", "learned"])
def test_tiles_surveyed_and_picked_in_worker_processes_give_the_threads_bytes(tmp_path, dense_patch, monkeypatch,
                                                                               method):
    """From the method's tile_processes_from (here 0) an in-process run surveys and picks its tiles in forkserver
    processes (for fps and voxel the survey counts voxels, for learned it also predicts the fill loss): the same
    file."""
    import pipeline.engine.processes as processes
    from model.registry import REGISTERED

    threads = tmp_path / "threads.laz"
    pipeline.run(dense_patch, threads, ratio=0.1, method=method, tile_size=4.0, seed=7, workers=2)
    monkeypatch.setattr(type(REGISTERED[method]), "tile_processes_from", 0)
    sent = []
    submit = processes.TilesElsewhere.submit

    def counted(self, fn, *args, **kwargs):
        sent.append((fn.__name__, fn in self.tile_work))
        return submit(self, fn, *args, **kwargs)

    monkeypatch.setattr(processes.TilesElsewhere, "submit", counted)
    elsewhere = tmp_path / "processes.laz"
    pipeline.run(dense_patch, elsewhere, ratio=0.1, method=method, tile_size=4.0, seed=7, workers=2)
    away = {name for name, is_away in sent if is_away}
    assert {"survey_tile", "simplify_tile"} <= away <= {"survey_tile", "count_cover", "simplify_tile"}
    # reading, and a stratified method's light reads of its surveys' files, stay on the threads
    assert {name for name, is_away in sent if not is_away} == {"bucket_piece"} | (
        {"reference_square", "exact_floor"} if method == "learned" else set())
    assert elsewhere.read_bytes() == threads.read_bytes()


@dataclass
class PickLoads:
    """What an in-process run planned (its tile plans, one per run) and how many points each pick step loaded
    ({picks_read_halo: [(tile id, points)]})."""

    plans: list[TilePlan] = field(default_factory=list)
    loaded: dict[bool, list[tuple[int, int]]] = field(default_factory=lambda: {True: [], False: []})


@pytest.fixture
def pick_loads(monkeypatch) -> PickLoads:
    """Record the runs' tile plans and their pick steps' loads (pipeline.engine.runner's own calls wrapped)."""
    import pipeline.engine.runner as runner

    seen = PickLoads()
    simplify, plan_tiles = runner.simplify_tile, runner.bucket_scan

    def planned(*args: Any, **kwargs: Any) -> tuple:
        found = plan_tiles(*args, **kwargs)
        seen.plans.append(found[0])
        return found

    def counted(job: TileJob, plan: TilePlan) -> TileOutcome:
        outcome = simplify(job, plan)
        seen.loaded[type(job.simplifier).picks_read_halo].append((outcome.tile_id, outcome.points))
        return outcome

    monkeypatch.setattr(runner, "simplify_tile", counted)
    monkeypatch.setattr(runner, "bucket_scan", planned)
    return seen


@pytest.mark.parametrize("method", ["learned", "stratified"])
def test_a_surveyed_fills_picks_load_the_core_alone_and_give_the_bytes_of_a_load_with_its_halo(
        tmp_path, dense_patch, monkeypatch, pick_loads, method):
    """The halo serves a fill's survey (its loss, saved for the core); its fill and hole cover pick among and
    measure the core alone, so its picks load no halo: every tile's pick step loads its cells' points only,
    and the file is the one a pick step that loaded the halo writes."""
    from model.registry import REGISTERED

    plans, loaded = pick_loads.plans, pick_loads.loaded
    settings = dict(ratio=0.1, method=method, tile_size=4.0, seed=7, workers=1)
    core_only = tmp_path / "core.laz"
    pipeline.run(dense_patch, core_only, **settings)
    monkeypatch.setattr(type(REGISTERED[method]), "picks_read_halo", True)
    with_halo = tmp_path / "halo.laz"
    pipeline.run(dense_patch, with_halo, **settings)
    cells = [{tile_id: tile.count for tile_id, tile in enumerate(plan.tiles)} for plan in plans]
    assert len(loaded[False]) == len(cells[0]) > 1
    assert all(points == cells[0][tile_id] for tile_id, points in loaded[False])
    assert sum(points for _, points in loaded[True]) > sum(cells[1].values())  # the halo was there to read
    assert with_halo.read_bytes() == core_only.read_bytes()


@pytest.mark.filterwarnings("error::RuntimeWarning")  # a resumed phase with no task left once warned of an empty mean
@pytest.mark.parametrize("method", ["voxel", "stratified"])
def test_a_run_that_failed_after_its_survey_resumes_to_the_same_bytes(tmp_path, dense_patch, monkeypatch, method):
    """A tile that fails after every survey is saved: the rerun reads the surveys back (voxel counts, fill
    loss) and the tiles already finished, and writes the bytes of a run that never failed (16 tiles, unmerged,
    so the surveys' counts share out the budgets). A survey file of an older format (here without its picks'
    radii and format number, as a 0.3.12 development build wrote them) is surveyed again, not read."""
    import pipeline.engine.runner as runner
    from pipeline.errors import PipelineError

    clean, out = tmp_path / "clean.laz", tmp_path / "out.laz"
    pipeline.run(dense_patch, clean, ratio=0.1, method=method, tile_size=4.0, seed=7, merge_tile_points=0)
    simplify_tile, calls = runner.simplify_tile, []

    def fails_from_the_second(job, plan):
        calls.append(job.tile_id)
        if len(calls) > 1:
            raise PipelineError(f"tile {job.tile_id}: a fault for the test")
        return simplify_tile(job, plan)

    monkeypatch.setattr(runner, "simplify_tile", fails_from_the_second)
    with pytest.raises(PipelineError, match="finished work kept in"):
        pipeline.run(dense_patch, out, ratio=0.1, method=method, tile_size=4.0, seed=7, merge_tile_points=0, workers=1)
    surveys = sorted(tmp_path.glob(".out.laz.work-*/survey-*.npz"))
    assert surveys and not out.exists()
    with np.load(surveys[0]) as saved:
        older = {name: saved[name] for name in saved.files if name not in ("survey_format", "even_radii")}
    with open(surveys[0], "wb") as file:
        np.savez(file, **older)
    monkeypatch.setattr(runner, "simplify_tile", simplify_tile)
    report = pipeline.run(dense_patch, out, ratio=0.1, method=method, tile_size=4.0, seed=7, merge_tile_points=0)
    assert report.resumed_tiles > 0
    assert out.read_bytes() == clean.read_bytes()


def test_seed_changes_random_output(tmp_path, dense_patch):
    a = pipeline.run(dense_patch, tmp_path / "a.las", ratio=0.1, method="random", workers=1, seed=1).output
    b = pipeline.run(dense_patch, tmp_path / "b.las", ratio=0.1, method="random", workers=1, seed=2).output
    assert a.read_bytes() != b.read_bytes()


def write_toronto3d_ply(path: Path, n: int = 20_000) -> np.ndarray:
    """A PLY in Toronto3D's schema plus one property LAS has no slot for."""
    rng = np.random.default_rng(9)
    vertex = np.zeros(n, dtype=[("x", "f8"), ("y", "f8"), ("z", "f8"), ("red", "u1"), ("green", "u1"),
                                ("blue", "u1"), ("scalar_Intensity", "f4"), ("scalar_GPSTime", "f8"),
                                ("scalar_ScanAngleRank", "f4"), ("scalar_Label", "f4"), ("scalar_Reflectance", "f4")])
    vertex["x"] = 627_000 + rng.uniform(0, 30, n)
    vertex["y"] = 4_842_000 + rng.uniform(0, 30, n)
    vertex["z"] = rng.uniform(0, 5, n)
    for channel in ("red", "green", "blue"):
        vertex[channel] = rng.integers(0, 256, n)
    vertex["scalar_Intensity"] = rng.integers(0, 3000, n)
    vertex["scalar_GPSTime"] = np.sort(rng.uniform(0, 60, n))
    vertex["scalar_ScanAngleRank"] = rng.uniform(-30, 30, n)
    vertex["scalar_Label"] = rng.integers(0, 9, n)
    vertex["scalar_Reflectance"] = rng.normal(size=n)
    PlyData([PlyElement.describe(vertex, "vertex")]).write(str(path))
    return vertex


def test_toronto3d_ply_maps_to_point_format_7(tmp_path):
    vertex = write_toronto3d_ply(tmp_path / "street.ply")
    out = tmp_path / "street.laz"
    pipeline.run(tmp_path / "street.ply", out, ratio=0.25, method="fps", workers=1, tile_size=10)
    las = laspy.read(out)
    assert las.header.version == "1.4" and las.header.point_format.id == 7
    assert len(las.points) == 5_000
    assert list(las.point_format.extra_dimension_names) == ["scalar_Reflectance"]
    # matched by x, y and z on the mm grid: random points can share an x, y pair there
    source = {(round(x * 1000), round(y * 1000), round(z * 1000)): i
              for i, (x, y, z) in enumerate(zip(vertex["x"], vertex["y"], vertex["z"]))}
    rows = [source[(round(x * 1000), round(y * 1000), round(z * 1000))] for x, y, z in zip(las.x, las.y, las.z)]
    src = vertex[rows]
    np.testing.assert_allclose(las.z, src["z"], atol=0.0006)
    np.testing.assert_array_equal(las.red, src["red"].astype(np.uint16) * 257)
    np.testing.assert_array_equal(las.intensity, src["scalar_Intensity"].astype(np.uint16))
    np.testing.assert_array_equal(las.gps_time, src["scalar_GPSTime"])
    np.testing.assert_array_equal(las.classification, src["scalar_Label"].astype(np.uint8))
    np.testing.assert_allclose(las.scan_angle * 0.006, src["scalar_ScanAngleRank"], atol=0.0031)
    np.testing.assert_array_equal(las.scalar_Reflectance, src["scalar_Reflectance"])


def test_zarr_output_replaced_only_with_overwrite(tmp_path, dense_patch):
    out = tmp_path / "o.zarr"
    pipeline.run(dense_patch, out, ratio=0.01, workers=1)
    with pytest.raises(pipeline.PipelineError, match="already exists"):
        pipeline.run(dense_patch, out, ratio=0.02, workers=1)
    assert zarr.open_group(str(out), mode="r")["x"].shape == (1_200,)
    pipeline.run(dense_patch, out, ratio=0.02, workers=1, overwrite=True)
    assert zarr.open_group(str(out), mode="r")["x"].shape == (2_400,)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["o.zarr"]  # no temporary or scratch left behind


def test_a_tile_sparse_for_the_radius_keeps_the_cover_it_needs(tmp_path):
    """Two 8 m tiles, the right one 50x sparser: its share of the count (80 of 4,080) cannot cover it at the
    run's hole radius, so its survey's picks fall short and a task of its own counts its cover there; its
    floor is that count, and its largest gap is the dense tile's, the radius (it keeps 520 of its 800)."""
    rng = np.random.default_rng(7)
    xy = np.concatenate([rng.uniform([0, 0], [8, 8], size=(40_000, 2)), rng.uniform([8, 0], [16, 8], size=(800, 2))])
    scan = write_flat_scene(tmp_path / "two.las", xy, 0.01, rng)
    report = pipeline.run(tmp_path / "two.las", tmp_path / "out.las", ratio=0.1, method="stratified", tile_size=8.0,
                          merge_tile_points=0, workers=1)
    out = laspy.read(tmp_path / "out.las")
    gap = cKDTree(np.column_stack([out.x, out.y, out.z])).query(np.column_stack([scan.x, scan.y, scan.z]))[0]
    right = xy[:, 0] >= 8
    assert report.output_points == 4_080
    assert (out.x - 500_000 >= 8).sum() > 5 * 80
    assert gap[right].max() <= 1.05 * gap[~right].max()


@pytest.mark.parametrize("method", ["stratified-detail", "learned"])
def test_budgets_follow_detail_across_tiles(tmp_path, method):
    """A flat 12 m x 4 m floor beside an equally dense 4 m x 4 m bumpy patch (each its own 4 m tiles): the
    stratified detail methods weigh tile against tile as one pass would, so the bumpy tile keeps more than
    its share of the count and the flat tiles less, while the total stays exact and the flat tiles keep the
    picks that cover them (their floor): no flat point farther than 1.5 even spacings (0.1 m) from a kept one.
    (Their floors were a point per voxel of the hole radius, about twice that cover: the flat tiles kept 60 %
    of their share, and now 49-52 %, with the same largest gap, 0.129 m.)"""
    rng = np.random.default_rng(5)
    xy = rng.uniform([0, 0], [16, 4], size=(64_000, 2))
    bumpy = xy[:, 0] >= 12
    z = np.where(bumpy, 0.4 * np.sin(6 * xy[:, 0]) * np.cos(6 * xy[:, 1]), 0.0) + 0.002 * rng.normal(size=len(xy))
    header = laspy.LasHeader(version="1.2", point_format=3)
    header.scales, header.offsets = [0.001] * 3, [500_000.0, 4_000_000.0, 0.0]
    las = laspy.LasData(header)
    las.x, las.y, las.z = 500_000 + xy[:, 0], 4_000_000 + xy[:, 1], z
    las.write(tmp_path / "floor.las")
    report = pipeline.run(tmp_path / "floor.las", tmp_path / "out.las", ratio=0.1, method=method, tile_size=4.0,
                          workers=1)
    out = laspy.read(tmp_path / "out.las")
    kept_x = out.x - 500_000
    assert report.output_points == 6_400
    share = (kept_x >= 12).mean()  # the bumpy patch holds a quarter of the points
    assert share > 0.3, share
    kept = np.column_stack([kept_x, out.y - 4_000_000, out.z])
    assert cKDTree(kept).query(np.column_stack([xy, z])[~bumpy])[0].max() < 0.15


def test_the_default_holds_its_chamfer_distance_within_the_bound_where_detail_draws_points_away(tmp_path):
    """The floor and bumpy patch above: the default gives the bumpy tile twice its share, which thinned the flat
    floor until the output's Chamfer distance was 1.58x that of one farthest point sampling of the whole scan
    (its hole radius, a multiple of the fill's spacing, closed no hole there). The run now narrows the radius
    until its survey's estimate is within its `chamfer_bound` (1.3x): measured 1.34x (the reference 1.0004x
    one farthest point sampling's, the estimate 3 % under the outcome; 0.3.11 measured 1.30x, its floor tile's
    cover read at the grid radius below, up to 9 % more picks than it needs), the bumpy tile still
    keeping more than twice its share, the flat floor's largest gap 0.129 -> 0.104 m; the run's report (and
    `pipeline run -v`) says the radius was narrowed, and that the flat tile's budget is now its cover floor (so
    farthest point sampling picks it alone). A bound of 100 gives the unbounded radius back, and no floor."""
    rng = np.random.default_rng(5)
    xy = rng.uniform([0, 0], [16, 4], size=(64_000, 2))
    bumpy = xy[:, 0] >= 12
    z = np.where(bumpy, 0.4 * np.sin(6 * xy[:, 0]) * np.cos(6 * xy[:, 1]), 0.0) + 0.002 * rng.normal(size=len(xy))
    las = write_flat_scene(tmp_path / "floor.las", xy, 0.0, rng)
    las.z = z
    las.write(tmp_path / "floor.las")
    scan = np.column_stack([xy, z])
    even = fps_simplify(Tile(scan, np.ones(len(scan), dtype=bool), np.zeros(3), seed=0), 6_400).indices
    even_chamfer = np.mean(cKDTree(scan[even]).query(scan)[0] ** 2)
    chamfers = []
    for bound in (None, 100.0):
        parameters = {} if bound is None else {"chamfer_bound": bound}
        report = pipeline.run(tmp_path / "floor.las", tmp_path / "out.las", ratio=0.1, tile_size=4.0, workers=1,
                              method_parameters=parameters, overwrite=True)
        radius, unbounded = report.hole_radius_m  # what `pipeline run -v` tells
        assert (radius < unbounded and "narrowed" in report.hole_line()) if bound is None else radius == unbounded
        assert report.floor_tiles == (1 if bound is None else 0) and report.tiles == 2
        assert ("1 of 2 tiles at their cover floor" in report.hole_line()) == (bound is None)
        out = laspy.read(tmp_path / "out.las")
        kept = np.column_stack([out.x - 500_000, out.y - 4_000_000, out.z])
        chamfers.append(np.mean(cKDTree(kept).query(scan)[0] ** 2) / even_chamfer)
        assert (kept[:, 0] >= 12).mean() > 0.45
    assert chamfers[0] <= 1.35 and chamfers[1] > 1.5, chamfers


def test_the_runs_reference_stands_for_one_farthest_point_sampling_of_the_whole_scan(tmp_path, monkeypatch):
    """A dense plane beside a volume of stray returns, in four tiles (unmerged): the Chamfer bound's reference a
    run measures (pipeline.engine.covers.fps_reference, observed as the run calls it) is within 10 % of the mean
    squared distance of one farthest point sampling of the whole scan to the same count (0.1 % measured), where
    the tiles' samplings at their shares of the count, its reference before 0.3.12, came out 3.8x it on the same
    scene in two tiles (test_chamfer_bound); the strays' three tiles are sampled past their survey's picks."""
    import pipeline.engine.phases as phases
    from model.cover import cover_order

    rng = np.random.default_rng(1)
    plane = np.column_stack([rng.uniform(0, 4, 40_000), rng.uniform(0, 4, 40_000), 0.01 * rng.normal(size=40_000)])
    strays = np.column_stack([rng.uniform(4, 16, 4_000), rng.uniform(0, 4, 4_000), rng.uniform(0, 4, 4_000)])
    scan = np.concatenate([plane, strays])
    las = write_flat_scene(tmp_path / "strays.las", scan[:, :2], 0.0, rng)
    las.z = scan[:, 2]
    las.write(tmp_path / "strays.las")
    measured, measure = [], phases.fps_reference

    def observed(*args: Any, **kwargs: Any) -> Any:
        measured.append(measure(*args, **kwargs))
        return measured[-1]

    monkeypatch.setattr(phases, "fps_reference", observed)
    pipeline.run(tmp_path / "strays.las", tmp_path / "out.las", ratio=0.1, tile_size=4.0, workers=1,
                 merge_tile_points=0)
    (surveys, reference, counted), = measured
    untiled = np.mean(cKDTree(scan[cover_order(scan, 4_400)]).query(scan)[0] ** 2)
    assert len(surveys) == 4 and counted == {1, 2, 3}
    assert reference == pytest.approx(untiled, rel=0.1), reference / untiled


def test_two_sites_far_apart_run_in_tiles_within_the_budget(tmp_path):
    """The corridor case in small: two 20 m sites 150 km apart, tiles under max_tile_points, exact count."""
    rng = np.random.default_rng(9)
    site = rng.uniform(0, 20, size=(20_000, 2))
    xy = np.concatenate([site, site + [150_000.0, 0.0]])
    header = laspy.LasHeader(version="1.2", point_format=3)
    header.scales, header.offsets = [0.001] * 3, [500_000.0, 4_000_000.0, 0.0]
    las = laspy.LasData(header)
    las.x, las.y, las.z = 500_000 + xy[:, 0], 4_000_000 + xy[:, 1], 0.05 * rng.normal(size=len(xy))
    las.write(tmp_path / "sites.las")
    report = pipeline.run(tmp_path / "sites.las", tmp_path / "out.las", ratio=0.1, method="fps", max_tile_points=5_000,
                          workers=1)
    assert report.output_points == 4_000 and report.tiles >= 8  # 40k points: at least 8 tiles of <= 5k


def station_scan(path: Path, corner: float, width: float) -> Path:
    """A 16 m square of 6,000 points (corners at 0 and 16, so grid cells start at whole metres) with 4,000
    more in the square of `width` from (corner, corner): a terrestrial scanner's standpoint."""
    rng = np.random.default_rng(1)
    spread = np.concatenate([[[0, 0], [16, 16]], rng.uniform(0, 16, size=(5_998, 2))])
    standpoint = corner + rng.uniform(0, width, size=(4_000, 2))
    xy = np.concatenate([spread, standpoint])
    header = laspy.LasHeader(version="1.2", point_format=1)
    header.scales, header.offsets = [0.001] * 3, [0.0] * 3
    las = laspy.LasData(header)
    las.x, las.y, las.z = xy[:, 0], xy[:, 1], rng.normal(0, 0.01, len(xy))
    las.classification = np.where(np.arange(len(xy)) % 10 == 0, 6, 2)
    las.write(path)
    return path


@pytest.mark.parametrize("method", ["fps", "learned"])
def test_a_cell_over_the_tile_limit_is_split_into_tiles_under_it(tmp_path, method):
    """A scanner's standpoint puts more than --max-tile-points into one grid cell (tile size / 8): the plan
    splits that cell on its sub-cells, so no task holds more than the limit; the output is exact, the
    points a class rule keeps whole are all kept, and any worker count gives the same file."""
    from pipeline.config import RunConfig
    from pipeline.engine.runner import run_scan

    scan = station_scan(tmp_path / "station.las", 3.5, 0.3)  # in one 1 m cell
    outputs, notes = [], []
    for workers, in_process in ((1, 10**9), (2, 0)):
        out = tmp_path / f"out{workers}.las"
        report = run_scan([scan], out, RunConfig(ratio=0.1, method=method, tile_size=8.0, max_tile_points=2_000,
                                                 workers=workers, in_process_points=in_process, keep_classes=(6,)),
                          note=notes.append)
        outputs.append(out.read_bytes())
        assert report.kept_whole == 1_000 and report.output_points == 1_000 + 900  # 0.1 of the other 9,000
        assert report.tiles >= 4  # the 8 m square's 4 tiles, the standpoint's cell now several more
    assert outputs[0] == outputs[1]
    assert not [line for line in notes if "--max-tile-points" in line]
    kept = laspy.read(tmp_path / "out1.las")
    assert (kept.classification == 6).sum() == 1_000
    near = (np.abs(kept.x - 3.65) < 0.15) & (np.abs(kept.y - 3.65) < 0.15)
    assert near.sum() >= 0.5 * 0.1 * 4_000  # the split standpoint keeps its share, not a seam-starved few


@pytest.mark.parametrize("method", ["fps", "learned"])
def test_a_pick_step_without_halo_loads_exactly_its_tiles_points_beside_split_cells(tmp_path, pick_loads, method):
    """A load without halo takes every row of its slices as core where the tile is whole cells (no cell
    lookups): those slices must hold its own points and no other, also where a neighbouring cell is split
    into sub-cell tiles, and the sub-cell tiles theirs."""
    from pipeline.config import RunConfig
    from pipeline.engine.runner import run_scan

    scan = station_scan(tmp_path / "station.las", 3.5, 0.3)
    run_scan([scan], tmp_path / "out.las", RunConfig(ratio=0.1, method=method, tile_size=8.0, max_tile_points=2_000,
                                                      workers=1))
    (plan,) = pick_loads.plans
    assert any(tile.sub is not None for tile in plan.tiles) and any(tile.sub is None for tile in plan.tiles)
    loads = pick_loads.loaded[True] + pick_loads.loaded[False]  # fps reads no halo anywhere, learned's picks none
    assert sorted(loads) == [(tile_id, tile.count) for tile_id, tile in enumerate(plan.tiles)]


def test_a_sub_cell_over_the_tile_limit_is_named_with_the_tile_size_that_splits_it(tmp_path):
    """A crowded cell is split down to sub-cells (tile size / 512) and no further: 4,000 points within
    one sub-cell stay one tile over the limit, and the run says so, and which tile size would split it."""
    from pipeline.config import RunConfig
    from pipeline.engine.runner import run_scan

    notes: list[str] = []
    report = run_scan([station_scan(tmp_path / "station.las", 3.506, 0.003)], tmp_path / "out.las",  # 1 sub-cell
                      RunConfig(ratio=0.1, method="fps", tile_size=8.0, max_tile_points=2_000), note=notes.append)
    assert report.output_points == 1_000
    crowded = [line for line in notes if "--max-tile-points" in line]
    assert len(crowded) == 1 and "1 sub-cell(s) of tile size / 512 hold more than --max-tile-points (2,000)" in crowded[0]
    assert "--tile-size of about 5.7 m or less" in crowded[0]  # 8 m * sqrt(2,000 / 4,000)


@pytest.mark.parametrize("method", ["learned", "fps"])
def test_a_scan_inside_one_crowded_cell_runs(tmp_path, method):
    """An object scanned closely (4,000 points within half a metre, over --max-tile-points in one cell): every
    occupied cell is split, which once crashed the plan's per-tile sums (numpy's bincount of no whole cell is
    int64, and the sub-cells' float sums could not be added to it)."""
    rng = np.random.default_rng(13)
    path = tmp_path / "object.las"
    write_flat_scene(path, rng.uniform(0, 0.5, size=(4_000, 2)), 0.05, rng)
    report = pipeline.run(path, tmp_path / "out.laz", ratio=0.1, method=method, tile_size=8.0,
                          max_tile_points=1_000, workers=1)
    assert report.output_points == len(laspy.read(tmp_path / "out.laz").points) == 400 and report.tiles > 1


def sparse_field_scan(path: Path) -> Path:
    """20,000 points over 64 x 64 m with a dense 8 x 8 m patch of 10,000: with 8 m tiles, 64 nominal
    tiles of about 300 points and one of 10,000."""
    rng = np.random.default_rng(12)
    xy = np.concatenate([[[0, 0], [64, 64]], rng.uniform(0, 64, size=(19_998, 2)), rng.uniform(0, 8, size=(10_000, 2))])
    header = laspy.LasHeader(version="1.2", point_format=1)
    header.scales, header.offsets = [0.001] * 3, [0.0] * 3
    las = laspy.LasData(header)
    las.x, las.y, las.z = xy[:, 0], xy[:, 1], rng.normal(0, 0.05, len(xy))
    las.write(path)
    return path


@pytest.mark.parametrize("method", ["fps", "learned"])
def test_merged_sparse_tiles_keep_the_exact_count_and_any_worker_count_gives_the_same_file(tmp_path, method):
    """--merge-tile-points: far fewer tiles on a sparse scan, the exact total, no area left empty, and the
    same bytes from one thread as from a two-worker cluster."""
    from pipeline.config import RunConfig
    from pipeline.engine.runner import run_scan

    scan = sparse_field_scan(tmp_path / "field.las")
    outputs, tiles = [], []
    for workers, in_process, merge in ((1, 10**9, 5_000), (2, 0, 5_000), (1, 10**9, 0)):
        out = tmp_path / f"out{workers}-{merge}.las"
        report = run_scan([scan], out, RunConfig(ratio=0.1, method=method, tile_size=8.0, max_tile_points=20_000,
                                                 merge_tile_points=merge, workers=workers,
                                                 in_process_points=in_process))
        assert report.output_points == 3_000
        outputs.append(out.read_bytes())
        tiles.append(report.tiles)
    assert outputs[0] == outputs[1]
    assert tiles[2] == 64 and tiles[0] <= 16
    kept = laspy.read(tmp_path / "out1-5000.las")
    squares = np.minimum(np.asarray(kept.x) // 8, 7) * 8 + np.minimum(np.asarray(kept.y) // 8, 7)
    assert len(np.unique(squares)) == 64  # no 8 m square of the field left empty by the merged tiles


def test_a_negative_merge_limit_gets_one_line(tmp_path):
    from click.testing import CliRunner

    from pipeline.apps.cli import cli

    scan = sparse_field_scan(tmp_path / "field.las")
    result = CliRunner().invoke(cli, ["run", str(scan), "-r", "0.1", "--merge-tile-points", "-1",
                                     "-o", str(tmp_path / "out.laz")])
    assert result.exit_code == 2 and "--merge-tile-points must be 0 (off) or more" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and not (tmp_path / "out.laz").exists()


def test_the_default_merge_limit_is_bounded_by_a_smaller_tile_limit(tmp_path):
    """Merging is on by default (50,000 points); --max-tile-points below that bounds merged tiles too, so a
    limit given for memory needs no second flag: the field's 4x4 squares (about 7,500 points) do not merge
    whole under a 2,000-point limit, its 2x2 quarters (about 1,900) do."""
    from pipeline.config import RunConfig
    from pipeline.engine.runner import run_scan

    scan = sparse_field_scan(tmp_path / "field.las")
    config = RunConfig(ratio=0.1, method="fps", tile_size=8.0, max_tile_points=2_000, in_process_points=10**9)
    assert config.merge_tile_points == 50_000 and config.merge_limit == 2_000
    assert RunConfig(method="paper").merge_limit == 0 == RunConfig(method="paper-refined").merge_limit
    report = run_scan([scan], tmp_path / "out.las", config)
    assert report.output_points == 3_000 and 4 < report.tiles < 64


@pytest.mark.parametrize("method", ["learned", "fps"])
def test_a_spot_of_twins_keeps_one_output_point_and_the_count_stays_exact(tmp_path, method):
    """A scanner's no-return spot (8,000 returns at one position above 32,000 of ground): its twins are surveyed
    and sampled as one point (model.geometry.PointTree, model.baselines.distinct_fps_order,
    model.selection.Tile.fill_mask), so the run keeps one of them and spends the rest of the count on the
    ground, still exactly round(ratio * N)."""
    rng = np.random.default_rng(8)
    xy = rng.uniform(0, 16, size=(40_000, 2))
    xy[:8_000] = [8.0, 8.0]
    path = tmp_path / "spot.las"
    las = write_flat_scene(path, xy, 0.01, rng)
    las.z[:8_000] = 2.0  # above the ground, as a sensor's origin: a position the output must keep
    las.write(path)
    result = pipeline.run(path, tmp_path / "out.laz", ratio=0.1, method=method, tile_size=6.0, workers=1)
    kept = laspy.read(tmp_path / "out.laz")
    assert len(kept.points) == result.output_points == 4_000
    at_spot = (np.asarray(kept.x) == 500_008.0) & (np.asarray(kept.y) == 4_000_008.0) & (np.asarray(kept.z) == 2.0)
    assert at_spot.sum() == 1
