"""The Python API: `pipeline.simplify` on a cloud in memory keeps what `pipeline.run` keeps on the same
points, in a progressive order; a caller's Dask client is reused, not replaced."""
from __future__ import annotations

import re

import laspy
import numpy as np
import pytest
from dask.distributed import Client, LocalCluster

import pipeline
from model.rules import kept_count
from pipeline.apps.in_memory import progressive_order


def record_set(records: np.ndarray) -> set[bytes]:
    return set(map(bytes, np.ascontiguousarray(records).view(np.dtype((np.void, records.dtype.itemsize)))))


@pytest.fixture(scope="module")
def client():
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None) as cluster, \
            Client(cluster) as dask_client:
        yield dask_client


@pytest.mark.parametrize("method", ["fps", "learned"])
def test_simplify_keeps_what_the_file_run_keeps(tmp_path, street_scan, client, method):
    las = laspy.read(street_scan)
    settings = dict(method=method, tile_size=20.0, client=client)
    kept = pipeline.simplify(las, 0.1, **settings)
    assert len(kept) == kept_count(0.1, len(las.points)) and len(np.unique(kept)) == len(kept)
    pipeline.run(street_scan, tmp_path / "out.las", ratio=0.1, **settings)
    assert record_set(las.points.array[kept]) == record_set(laspy.read(tmp_path / "out.las").points.array)


def test_simplify_an_array_in_a_progressive_order(client):
    rng = np.random.default_rng(0)
    xyz = np.column_stack([rng.uniform(0, 80, 30_000), rng.uniform(0, 40, 30_000), rng.normal(0, 0.05, 30_000)])
    kept = pipeline.simplify(xyz, 0.2, method="fps", tile_size=20.0, client=client)
    assert len(kept) == 6_000 and np.array_equal(kept, pipeline.simplify(xyz, 0.2, method="fps", tile_size=20.0,
                                                                           client=client))
    head = xyz[kept[:300], :2]  # the first 5 % already spread over the whole cloud, tile by tile
    occupied = np.unique(np.floor(head / 20).astype(int), axis=0)
    assert len(occupied) == 8
    with pytest.raises(pipeline.PipelineError, match=r"\(n, 3\) array"):
        pipeline.simplify(xyz[:, :2], 0.2, client=client)


def test_simplify_an_array_keeps_what_the_file_run_keeps_on_the_same_points(tmp_path, client):
    """An array on the 0.1 mm grid that simplify quantises to, and the same points as a LAS file: the same picks."""
    rng = np.random.default_rng(5)
    steps = np.column_stack([rng.integers(0, 600_000, 40_000), rng.integers(0, 300_000, 40_000),
                             rng.integers(0, 2_000, 40_000)])
    xyz = steps * 1e-4 + [500_000.0, 4_000_000.0, 10.0]
    header = laspy.LasHeader(version="1.4", point_format=6)
    header.offsets, header.scales = xyz.min(axis=0), [1e-4] * 3
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz.T
    las.write(tmp_path / "same.las")
    settings = dict(method="fps", tile_size=20.0, client=client)
    kept = pipeline.simplify(xyz, 0.1, **settings)
    pipeline.run(tmp_path / "same.las", tmp_path / "out.las", ratio=0.1, **settings)
    from_file = laspy.read(tmp_path / "out.las")
    assert set(map(tuple, np.round(xyz[kept], 4))) == set(map(tuple, np.round(from_file.xyz, 4)))


def test_progressive_order_takes_each_tile_in_proportion():
    order = progressive_order(np.array([4, 2]))
    assert order.tolist() == [0, 4, 1, 2, 5, 3]


def test_the_callers_client_is_reused(tmp_path, street_scan, client):
    before = set(client.scheduler_info()["workers"])
    pipeline.run(street_scan, tmp_path / "a.laz", ratio=0.05, method="random", client=client)
    assert set(client.scheduler_info()["workers"]) == before and client.status == "running"
    summary = pipeline.info(tmp_path / "a.laz")
    assert summary["points"] == kept_count(0.05, 60_000) and summary["provenance"]["method"] == "random"
    reference, scores = pipeline.evaluate(street_scan, [tmp_path / "a.laz"], sample=0)
    assert reference.unit.name == "metre" and scores[0].points == summary["points"]


def test_in_process_points_must_not_be_negative():
    with pytest.raises(pipeline.PipelineError, match="in-process-points"):
        pipeline.RunConfig(in_process_points=-1).validated()


def test_a_runs_notes_reach_python_callers_as_warnings(tmp_path):
    """What `pipeline run` notes on stderr, `pipeline.run` warns: here, a scan without a CRS taken as metres."""
    header = laspy.LasHeader(version="1.2", point_format=1)
    header.scales, header.offsets = [0.01] * 3, [0.0] * 3
    las = laspy.LasData(header)
    las.x, las.y, las.z = np.random.default_rng(2).uniform(0, 30, (3, 5_000))
    las.write(tmp_path / "no_crs.las")
    with pytest.warns(pipeline.PipelineNote, match="no usable CRS: its coordinates are taken as metres"):
        report = pipeline.run(tmp_path / "no_crs.las", tmp_path / "out.las", ratio=0.1, method="random")
    assert report.output_points == 500
    with pytest.warns(pipeline.PipelineNote, match="no usable CRS"):  # simplify dropped them
        assert len(pipeline.simplify(las, 0.1, method="random")) == 500


def test_simplify_speaks_of_the_points_and_reads_a_cloud_it_wrote_before(tmp_path):
    """A failure names the caller's points, not the temporary file they went through (nor a work folder to
    resume from that is gone with it); a LasData that already holds simplify's index dimension (read back
    from a file of an earlier simplify) is simplified, not a ValueError."""
    from pipeline.apps.in_memory import INDEX_DIMENSION

    header = laspy.LasHeader(version="1.4", point_format=6)
    header.add_extra_dim(laspy.ExtraBytesParams(INDEX_DIMENSION, "u2"))
    las = laspy.LasData(header)
    las.x, las.y, las.z = np.random.default_rng(3).uniform(0, 30, (3, 2_000))
    with pytest.raises(pipeline.PipelineError, match=r"^the points: --ratio 1e-09 keeps 0 of 2000 points$"):
        pipeline.simplify(las, 1e-9, method="random")
    kept = pipeline.simplify(las, 0.1, method="random")
    assert len(kept) == len(set(kept)) == 200 and kept.max() < 2_000


def test_numpy_numbers_are_taken_as_python_s(tmp_path):
    """A notebook's ratio is often a numpy scalar and its levels an array: np.float32(0.5) was refused as
    'not in (0, 1]' and an array of levels failed on its truth value."""
    rng = np.random.default_rng(2)
    xyz = rng.uniform(0, 20, (3_000, 3))
    assert len(pipeline.simplify(xyz, np.float32(0.1), method="fps")) == 300
    header = laspy.LasHeader(version="1.4", point_format=6)
    header.scales = [0.001] * 3
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz.T
    las.write(tmp_path / "in.las")
    pipeline.run(tmp_path / "in.las", tmp_path / "out.las", levels=np.array([0.2, 0.1]), method="fps")
    assert [laspy.read(tmp_path / f"out.r{r}.las").header.point_count for r in ("0.2", "0.1")] == [600, 300]


def test_an_empty_cloud_is_refused_naming_the_cloud_not_a_temporary_file():
    with pytest.raises(pipeline.PipelineError, match="^points: the array holds no points"):
        pipeline.simplify(np.empty((0, 3)), 0.1)


@pytest.mark.parametrize("settings, said", [
    (dict(workers="2"), "workers must be a whole number, got '2'"),
    (dict(workers=2.5), "workers must be a whole number, got 2.5"),
    (dict(ratio=True), "ratio must be a number, got True"),
    (dict(levels=0.2), "levels must be a list of numbers, got 0.2"),
    (dict(allow_geographic="no"), "allow_geographic must be true or false, got 'no'"),  # "no" is truthy
    (dict(method_parameters=[("slack", 0.5)]), "method_parameters must be a dict of name: value"),
    (dict(seed=1.5), "seed must be a whole number, got 1.5"),
    (dict(seed=-1), "--seed must be a whole number, 0 or more, got -1"),
])
def test_keyword_arguments_of_the_wrong_type_fail_before_any_work(tmp_path, street_scan, settings, said):
    """The API's settings are checked as a config file's are: a wrong type is one line, not a TypeError deep in
    the run, nor a value taken for another ("no" for True)."""
    out = tmp_path / "out.laz"
    with pytest.raises(pipeline.PipelineError, match=re.escape(said)) as caught:
        pipeline.run(street_scan, out, **{"ratio": 0.1, **settings})
    assert "\n" not in str(caught.value) and not out.exists()


def test_evaluate_and_compare_take_one_path_ratio_or_method_and_check_them_first(tmp_path, street_scan):
    """One candidate path, one ratio, one method name are taken as one (a string was read as its characters);
    a ratio that keeps no point or a negative sample fails before the first run."""
    out = tmp_path / "out.laz"
    pipeline.run(street_scan, out, ratio=0.1, method="random", workers=1)
    _, scores = pipeline.evaluate(street_scan, str(out), sample=0)
    assert [score.path for score in scores] == [out]
    with pytest.raises(pipeline.PipelineError, match="--sample must be a whole number"):
        pipeline.evaluate(street_scan, [out], sample=-5)
    with pytest.raises(pipeline.PipelineError, match="--ratio 1e-09 keeps 0 of"):
        pipeline.compare(street_scan, ratios=(0.1, 1e-9), methods="random", out_dir=tmp_path / "compare")
    assert not (tmp_path / "compare" / "runs").exists()


def test_simplify_reads_a_crs_held_in_an_evlr(tmp_path, client):
    """LAS 1.4 may hold its WKT in an extended VLR: simplify of the LasData takes its unit (feet) as run does
    on the file, so both cut the same tiles and keep the same points (the EVLR was dropped: metres assumed)."""
    from laspy.vlrs.vlrlist import VLRList

    from tests.test_units import write_patch

    write_patch(tmp_path / "feet.las", 2992, 0.3048)
    las = laspy.read(tmp_path / "feet.las")
    las.header.evlrs = VLRList([v for v in las.header.vlrs if v.user_id == "LASF_Projection"])
    las.header.vlrs = VLRList([v for v in las.header.vlrs if v.user_id != "LASF_Projection"])
    las.write(tmp_path / "evlr.las")
    las = laspy.read(tmp_path / "evlr.las")
    assert not las.header.vlrs.get("WktCoordinateSystemVlr") and las.header.evlrs
    settings = dict(method="fps", tile_size=20.0, client=client)
    with pytest.warns(pipeline.PipelineNote, match="the scan is in foot"):
        pipeline.run(tmp_path / "evlr.las", tmp_path / "out.las", ratio=0.1, **settings)
    kept = pipeline.simplify(las, 0.1, **settings)
    assert record_set(las.points.array[kept]) == record_set(laspy.read(tmp_path / "out.las").points.array)
