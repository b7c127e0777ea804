"""`pipeline eval` and `pipeline compare` on small generated scans: tables, JSON, PNGs, one-line errors."""
from __future__ import annotations

import json
from pathlib import Path

import laspy
import matplotlib.image
import numpy as np
import pyproj
import pytest
import zarr
from click.testing import CliRunner

import pipeline
import pipeline.apps.comparison
from pipeline.apps.cli import cli
from pipeline.apps.comparison import RunOptions, compare
from pipeline.apps.scoring import METRIC_COLUMNS
from pipeline.simulate import write_street_scan

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def scan(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("eval") / "street.laz"
    write_street_scan(path, n_points=5_000, seed=4)
    return path


def subset_las(scan: Path, path: Path, step: int) -> Path:
    las = laspy.read(scan)
    las.points = las.points[np.arange(0, len(las.points), step)]  # a copy: laspy writes contiguous buffers only
    las.write(path)
    return path


def subset_zarr(scan: Path, path: Path, step: int) -> Path:
    las = laspy.read(scan)
    group = zarr.open_group(str(path), mode="w", zarr_format=3)
    for name in "xyz":
        group.create_array(name, data=np.asarray(las[name], dtype=np.float64)[::step])
    return path


def run_cli(*args: str):
    return CliRunner().invoke(cli, list(args), prog_name="pipeline")


def test_eval_prints_a_row_per_candidate_and_json(scan, tmp_path):
    las_candidate = subset_las(scan, tmp_path / "half.las", 2)
    zarr_candidate = subset_zarr(scan, tmp_path / "quarter.zarr", 4)
    text = run_cli("eval", str(scan), str(las_candidate), str(zarr_candidate))
    assert text.exit_code == 0, text.output
    rows = [line for line in text.output.splitlines() if line.startswith(("| " + str(tmp_path)))]
    assert len(rows) == 2 and "half.las" in rows[0] and "quarter.zarr" in rows[1]
    assert all(title in text.output for title, _, _ in METRIC_COLUMNS)
    result = run_cli("eval", str(scan), str(las_candidate), str(zarr_candidate), "--json")
    report = json.loads(result.output)
    half, quarter = report["candidates"]
    assert half["points"] == 2_500 and quarter["points"] == 1_250
    assert 0 < half["chamfer"] < quarter["chamfer"] and 0 < half["hausdorff"] <= quarter["hausdorff"]


def test_eval_of_the_reference_itself_is_zero(scan):
    report = json.loads(run_cli("eval", str(scan), str(scan), "--json").output)
    scores = report["candidates"][0]
    assert scores["chamfer"] == 0 and scores["hausdorff"] == 0
    assert scores["normal_consistency"] == pytest.approx(0, abs=1e-9) and scores["sdm"] == pytest.approx(0, abs=1e-9)


def test_eval_sample_takes_whole_cells(scan, tmp_path):
    candidate = subset_las(scan, tmp_path / "half.las", 2)
    report = json.loads(run_cli("eval", str(scan), str(candidate), "--json", "--sample", "1000").output)
    assert report["reference_points"] == 5_000 and 1_000 <= report["evaluated_reference_points"] < 5_000
    assert report["sample_cells"] > 0 and report["candidates"][0]["evaluated_points"] < 2_500


def test_sampled_scores_see_past_the_cell_borders(tmp_path):
    # the sampled points are points of the whole scan, and with the margin they keep their nearest points,
    # so a sampled maximum cannot pass the exact one (cropped to the cells alone it came to 1.9x)
    source = tmp_path / "street.laz"
    write_street_scan(source, n_points=20_000, seed=5)
    candidate = tmp_path / "fps.laz"
    pipeline.run(source, candidate, ratio=0.2, method="fps", workers=1)
    exact, sampled = (json.loads(run_cli("eval", str(source), str(candidate), "--json", "--sample", n).output)
                      for n in ("0", "5000"))
    assert sampled["sample_cells"] > 0 and 5_000 <= sampled["evaluated_reference_points"] < 20_000
    assert 0 < sampled["candidates"][0]["hausdorff"] <= exact["candidates"][0]["hausdorff"]
    assert sampled["candidates"][0]["chamfer"] == pytest.approx(exact["candidates"][0]["chamfer"], rel=0.2)


def test_eval_missing_file_is_one_line(scan, tmp_path):
    result = run_cli("eval", str(scan), str(tmp_path / "nope.laz"))
    assert result.exit_code == 2
    assert result.stderr.strip().splitlines() == [f"pipeline: error: {tmp_path / 'nope.laz'}: no such file"]


@pytest.mark.parametrize("args", [["--methods", "fps,nope"], ["--ratios", "0.1,2"], ["--ratios", "a"]])
def test_compare_bad_options_are_one_line(scan, tmp_path, args):
    result = run_cli("compare", str(scan), "--out-dir", str(tmp_path / "c"), *args)
    assert result.exit_code == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("pipeline: error: ")


def test_compare_writes_table_json_and_plots(tmp_path):
    source = tmp_path / "street.laz"
    write_street_scan(source, n_points=20_000, seed=5)
    methods, ratios = ["fps", "random", "voxel"], [0.2, 0.1]
    written = compare(source, ratios, methods, tmp_path / "out", RunOptions(workers=1))
    table = (tmp_path / "out" / "compare.md").read_text()
    rows = [line for line in table.splitlines() if line.startswith("| ") and line.split("|")[1].strip() in methods]
    assert sorted((r.split("|")[1].strip(), r.split("|")[2].strip()) for r in rows) == sorted(
        (m, f"{r:g}") for m in methods for r in ratios)
    report = json.loads((tmp_path / "out" / "compare.json").read_text())
    assert len(report["results"]) == 6 and {r["points"] for r in report["results"]} == {4_000, 2_000}
    pngs = [p for p in written if p.suffix == ".png"]
    assert len(pngs) == len(METRIC_COLUMNS) + 1
    for png in pngs:
        assert png.read_bytes()[:8] == PNG_SIGNATURE
        assert matplotlib.image.imread(png).ndim == 3


def write_line_scan(path: Path, x: np.ndarray) -> Path:
    """Points at `x` along a straight line in UTM 10N, with random heights."""
    header = laspy.LasHeader(point_format=3, version="1.4")
    header.add_crs(pyproj.CRS.from_epsg(32610))
    las = laspy.LasData(header)
    las.x, las.y, las.z = x, np.full(len(x), 3.0), np.random.default_rng(6).uniform(0, 1, len(x))
    las.write(path)
    return path


def test_compare_pictures_a_result_with_no_point_in_the_region(tmp_path, monkeypatch):
    """A result none of whose points lies in the pictured region (the reference's most curved cell) gets an
    empty panel, not a failure: a 500 m line of 200k points pictured in a 50 m cell, a result of two points
    beyond it."""
    from pipeline.apps.comparison import Entry, write_region
    from pipeline.apps.scoring import prepare_reference, score

    shown = []  # the result panels region_view drew: (xyz, curvature) by (method, ratio)
    real_view = pipeline.apps.comparison.region_view

    def recording_view(reference, panels, *args):
        shown.append(panels)
        return real_view(reference, panels, *args)

    monkeypatch.setattr(pipeline.apps.comparison, "region_view", recording_view)
    reference = prepare_reference(write_line_scan(tmp_path / "line.las", np.linspace(0, 500, 200_000)), 0, 0,
                                  pipeline.progress.Progress())
    region = pipeline.apps.comparison.detailed_region(reference)
    cell_x = region.origin[0] + region.side * (int(region.chosen[0]) // region.shape[1])  # the cell's west edge
    outside = cell_x + region.side * (1.5 if cell_x + region.side * 1.5 < 500 else -0.5)
    result = write_line_scan(tmp_path / "two.las", np.array([outside, outside + 0.1]))
    written = write_region(reference, [Entry("random", 1e-5, score(reference, result))], ["random"], [1e-5], tmp_path)
    xyz, curvature = shown[0][("random", 1e-5)]
    assert len(xyz) == len(curvature) == 0
    assert written.read_bytes()[:8] == PNG_SIGNATURE
    for n in (0, 1, 2):  # too few points for a neighbourhood still give a curvature per point
        assert pipeline.apps.comparison.region_curvature(np.random.default_rng(n).uniform(size=(n, 3))).shape == (n,)


def test_a_candidate_away_from_the_reference_is_refused(tmp_path):
    """A candidate whose points all lie away from the reference (another place, or another CRS where one file
    has none) is refused in one line: its Chamfer distance would be the distance between the places."""
    reference = write_line_scan(tmp_path / "line.las", np.linspace(0, 500, 2_000))
    away = write_line_scan(tmp_path / "away.las", np.linspace(10_000, 10_500, 200))
    with pytest.raises(pipeline.PipelineError, match="away.las: no points where .*line.las was evaluated"):
        pipeline.evaluate(reference, [away], sample=0)
    near = write_line_scan(tmp_path / "near.las", np.linspace(0, 500, 200))
    assert pipeline.evaluate(reference, [near], sample=0)[1][0].points == 200
