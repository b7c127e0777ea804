"""Lengths are metres whatever the scan's unit: a scan in feet is tiled as the same scan in metres."""
from __future__ import annotations

import json
from pathlib import Path

import laspy
import numpy as np
import pyproj
import pytest
from click.testing import CliRunner
from scipy.spatial import cKDTree

import pipeline
from pipeline.apps.cli import cli
from pipeline.io.crs import length_unit

STEP = 0.001 * np.sqrt(2)  # grid step in metres: no grid point falls exactly on a cell border in metres or feet


def write_patch(path: Path, epsg: int | None, metres_per_unit: float, n: int = 40_000, seed: int = 1) -> None:
    """A 60 m x 30 m gently curved patch on a grid of STEP metres, written in the unit of `epsg` (none if
    None): the same integer records whatever the unit, only scale and offsets differ, so a scan in feet
    and its copy in metres hold exactly the same points."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, [60, 30], size=(n, 2))
    metres = np.column_stack([xy, 0.3 * np.sin(xy[:, 0] / 3) + 0.01 * rng.normal(size=n)])
    header = laspy.LasHeader(version="1.4", point_format=6)
    header.scales = [STEP / metres_per_unit] * 3
    header.offsets = np.array([1_000.0, 2_000.0, 0.0]) / metres_per_unit  # small: no float rounding at borders
    if epsg is not None:
        header.add_crs(pyproj.CRS.from_epsg(epsg))
    las = laspy.LasData(header)
    las.X, las.Y, las.Z = np.round(metres / STEP).astype(np.int32).T
    las.write(path)


@pytest.mark.parametrize("epsg, unit", [(2992, "foot"), (2227, "US survey foot")])
def test_a_scan_in_feet_is_planned_and_thinned_as_in_metres(tmp_path, epsg, unit):
    """The same points in metres and in feet: the same tiles and, with random's per-tile seeds, the same kept
    points; with lengths taken as feet, the feet run would cut 3.3x more tiles per side."""
    factor = pyproj.CRS.from_epsg(epsg).axis_info[0].unit_conversion_factor
    write_patch(tmp_path / "m.las", 32610, 1.0)
    write_patch(tmp_path / "ft.las", epsg, factor)
    assert length_unit(laspy.open(tmp_path / "ft.las").header).name == unit
    settings = dict(ratio=0.1, method="random", tile_size=12.0, overlap=1.0, workers=1)
    in_metres = pipeline.run(tmp_path / "m.las", tmp_path / "m_out.las", **settings)
    in_feet = pipeline.run(tmp_path / "ft.las", tmp_path / "ft_out.las", **settings)
    assert in_feet.tiles == in_metres.tiles and in_feet.output_points == in_metres.output_points
    kept_m = laspy.read(tmp_path / "m_out.las").xyz
    kept_ft = laspy.read(tmp_path / "ft_out.las").xyz * factor
    distance = cKDTree(kept_m).query(kept_ft)[0]
    assert np.all(distance < 1e-6)


def test_the_run_says_once_that_lengths_are_converted_or_assumed(tmp_path):
    write_patch(tmp_path / "ft.las", 2992, 0.3048, n=5_000)
    write_patch(tmp_path / "none.las", None, 1.0, n=5_000)
    runner = CliRunner()
    feet = runner.invoke(cli, ["run", str(tmp_path / "ft.las"), "--ratio", "0.1", "--method", "random", "-w", "1",
                               "-o", str(tmp_path / "a.las")])
    bare = runner.invoke(cli, ["run", str(tmp_path / "none.las"), "--ratio", "0.1", "--method", "random", "-w", "1",
                               "-o", str(tmp_path / "b.las")])
    assert feet.exit_code == 0 and bare.exit_code == 0
    assert feet.stderr.count("note: lengths are in metres and the scan is in foot") == 1
    assert bare.stderr.count("note: the scan has no usable CRS: its coordinates are taken as metres") == 1


def test_info_and_eval_say_the_unit_and_eval_refuses_mixed_units(tmp_path):
    write_patch(tmp_path / "ft.las", 2227, 1200 / 3937, n=5_000)
    write_patch(tmp_path / "m.las", 32610, 1.0, n=5_000)
    runner = CliRunner()
    info = json.loads(runner.invoke(cli, ["info", str(tmp_path / "ft.las"), "--json"]).stdout)
    assert info["epsg"] == 2227 and info["horizontal_unit"] == "US survey foot" and not info["horizontal_unit_assumed"]
    assert info["density"] == pytest.approx(5_000 / info["area"])
    scored = runner.invoke(cli, ["eval", str(tmp_path / "ft.las"), str(tmp_path / "ft.las")])
    assert scored.exit_code == 0 and "Hausdorff in US survey foot, CD (squared distances) in square US survey foot" in scored.stdout
    mixed = runner.invoke(cli, ["eval", str(tmp_path / "ft.las"), str(tmp_path / "m.las")])
    assert mixed.exit_code == 2 and "in metre" in mixed.stderr and "in US survey foot" in mixed.stderr


def test_eval_refuses_a_candidate_in_another_crs_of_the_same_unit(tmp_path):
    """The same coordinates in UTM zones 10N and 11N are places 700 km apart: scored as one, they came out
    perfect. `run` refuses inputs in different CRSs; eval (and report, through it) now refuses them too."""
    write_patch(tmp_path / "z10.las", 32610, 1.0, n=5_000)
    write_patch(tmp_path / "z11.las", 32611, 1.0, n=5_000)
    mixed = CliRunner().invoke(cli, ["eval", str(tmp_path / "z10.las"), str(tmp_path / "z11.las")])
    assert mixed.exit_code == 2 and "UTM zone 11N" in mixed.stderr and "UTM zone 10N" in mixed.stderr, mixed.stderr
    same = CliRunner().invoke(cli, ["eval", str(tmp_path / "z10.las"), str(tmp_path / "z10.las")])
    assert same.exit_code == 0, same.stderr


def test_a_geographic_label_on_coordinates_no_degree_can_take_is_metres_for_info_as_for_run(tmp_path):
    """lone-star.laz declares WGS 84 on UTM-sized coordinates: the run takes them as metres (no degree check
    fires), while `info` and `eval` said 'degree (assumed)'. All three now say metres, assumed."""
    write_patch(tmp_path / "mislabelled.las", 4326, 1.0, n=5_000)  # x 1000-1060, y 2000-2030: not degrees
    info = json.loads(CliRunner().invoke(cli, ["info", str(tmp_path / "mislabelled.las"), "--json"]).stdout)
    assert info["horizontal_unit"] == "metre" and info["horizontal_unit_assumed"]
    with pytest.warns(pipeline.PipelineNote, match="its coordinates are taken as metres"):
        pipeline.run(tmp_path / "mislabelled.las", tmp_path / "out.las", ratio=0.1, method="fps", workers=1)
