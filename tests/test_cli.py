"""The command line: help, info, and one-line errors with a non-zero exit and no output file."""
from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import laspy
import numpy as np
import pytest
import trimesh

from tests.conftest import shared_file


def cli(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "pipeline.apps.cli", *args], capture_output=True, text=True, cwd=cwd,
                          timeout=600)


def small_las(path: Path, n: int = 2_000) -> Path:
    header = laspy.LasHeader(version="1.4", point_format=6)
    header.scales, header.offsets = [0.01] * 3, [0.0] * 3
    las = laspy.LasData(header)
    rng = np.random.default_rng(0)
    las.x, las.y, las.z = rng.uniform(0, 50, n), rng.uniform(0, 50, n), rng.uniform(0, 5, n)
    las.write(path)
    return path


def assert_one_line_error(result: subprocess.CompletedProcess, *words: str) -> None:
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("pipeline: error: "), result.stderr
    assert "Traceback" not in result.stderr
    for word in words:
        assert word in lines[0], lines[0]


def test_help_reads_like_a_tool():
    result = cli("run", "--help")
    assert result.returncode == 0
    for flag in ("--ratio", "--output", "--method", "--tile-size", "--overlap", "--workers", "--memory-limit",
                 "--config", "--seed"):
        assert flag in result.stdout


def test_the_command_line_imports_laspy_without_its_http_client_and_leaves_requests_importable():
    """laspy's `import requests` (for remote COPC) is a fifth of a small run's wall; the CLI reads local files."""
    if importlib.util.find_spec("requests") is None:
        pytest.skip("requests is not installed: laspy imports no HTTP client anyway")
    probe = ("import sys, importlib.util, pipeline.apps.cli, laspy.copc; "
             "print(laspy.copc.requests is None, 'requests' in sys.modules); "
             "print(importlib.util.find_spec('requests') is None or __import__('requests').Session is not None)")
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == ["True", "False", "True"]  # laspy without it, requests not loaded, importable


def test_the_command_line_leaves_the_scoring_and_report_code_to_the_commands_that_use_them():
    """`pipeline run` needs neither (with model.metrics they were 13-18 ms of every run); `report` imports them."""
    probe = ("import sys, pipeline.apps.cli; "
             "print(*(name in sys.modules for name in ('pipeline.apps.scoring', 'pipeline.apps.visual.report_region', "
             "'model.metrics')))")
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == ["False"] * 3


@pytest.mark.parametrize("entry", ["pipeline.apps.cli", "pipeline.engine.tile_server"])
def test_the_command_line_and_its_tile_processes_load_pyproj_only_to_parse_a_crs(entry):
    """laspy imports pyproj up front (70-90 ms with what it brings); a scan without a CRS (a PLY) never needs it,
    and one with a CRS is still parsed: laspy's own parsing imports it then."""
    pytest.importorskip("pyproj")
    probe = (f"import sys, {entry}, laspy; print('pyproj' in sys.modules); "
             "import pyproj; from pipeline.io.crs import parsed_crs; "
             "header = laspy.LasHeader(point_format=3, version='1.4'); header.add_crs(pyproj.CRS.from_epsg(32633)); "
             "print(parsed_crs(header).to_epsg())")
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == ["False", "32633"]


def test_info_summary_and_json():
    path = shared_file("bcts_1.laz")
    text = cli("info", str(path))
    assert text.returncode == 0 and "531,662" in text.stdout and "BC Albers" in text.stdout
    summary = json.loads(cli("info", str(path), "--json").stdout)
    assert summary["points"] == 531_662 and summary["point_format"] == 1 and summary["las_version"] == "1.2"
    assert summary["scale"] == [0.01, 0.01, 0.01] and "gps_time" in summary["dimensions"]
    assert summary["epsg"] == 3005 and summary["horizontal_unit"] == "metre" and summary["compressed"]
    assert sum(summary["class_counts"].values()) == sum(summary["return_counts"].values()) == 531_662
    assert summary["file_size"] == path.stat().st_size


def test_info_describes_a_file_of_no_point(tmp_path):
    """info describes a file of no point (it refused it as a run does)."""
    header = laspy.LasHeader(version="1.4", point_format=6)
    laspy.LasData(header).write(tmp_path / "empty.las")
    text = cli("info", str(tmp_path / "empty.las"))
    assert text.returncode == 0 and "points:        0" in text.stdout and "classes:       none (no points)" in text.stdout
    assert json.loads(cli("info", str(tmp_path / "empty.las"), "--json").stdout)["class_counts"] == {}


def test_info_counts_the_points_of_a_file_whose_header_bounds_miss_them():
    """A run measures such bounds anew and goes on; info refused the file."""
    misbounded = shared_file("edge-cases/simple1_3.las")  # bounds written unscaled
    summary = json.loads(cli("info", str(misbounded), "--json").stdout)
    assert sum(summary["class_counts"].values()) == summary["points"] == 999


def test_info_counts_classes_and_returns_from_the_points_and_reads_compression_from_the_header(tmp_path):
    """Counts come from the points, not the header's per-return counts; a LAZ file named .las is compressed."""
    header = laspy.LasHeader(version="1.4", point_format=6)
    las = laspy.LasData(header)
    las.x, las.y, las.z = np.arange(10.0), np.arange(10.0), np.zeros(10)
    las.classification = [2] * 7 + [6] * 3
    las.return_number = [1] * 6 + [2] * 4
    las.number_of_returns = [2] * 10
    las.write(tmp_path / "disguised.laz")
    (tmp_path / "disguised.laz").rename(tmp_path / "disguised.las")
    summary = json.loads(cli("info", str(tmp_path / "disguised.las"), "--json").stdout)
    assert summary["compressed"] and summary["class_counts"] == {"2": 7, "6": 3}
    assert summary["return_counts"] == {"1": 6, "2": 4}
    header_only = json.loads(cli("info", str(tmp_path / "disguised.las"), "--json", "--header-only").stdout)
    assert "class_counts" not in header_only and header_only["points"] == 10


@pytest.mark.parametrize("ratio", ["0", "1.5", "nan", "-0.1"])
def test_ratio_outside_range(tmp_path, ratio):
    source = small_las(tmp_path / "in.las")
    assert_one_line_error(cli("run", str(source), "--ratio", ratio, "-o", str(tmp_path / "o.las")), "ratio")
    assert not (tmp_path / "o.las").exists()


def test_missing_input(tmp_path):
    assert_one_line_error(cli("run", str(tmp_path / "nope.laz"), "--ratio", "0.1"), "nope.laz", "no such file")


def test_existing_output_needs_overwrite(tmp_path):
    source = small_las(tmp_path / "in.las")
    out = tmp_path / "o.las"
    out.write_bytes(b"keep me")
    assert_one_line_error(cli("run", str(source), "--ratio", "0.5", "-o", str(out)), "already exists")
    assert out.read_bytes() == b"keep me"
    small_las(out, n=10)  # --overwrite replaces only a file of the output's kind (tests/test_hostile.py)
    ok = cli("run", str(source), "--ratio", "0.5", "-o", str(out), "--overwrite", "-q", "-w", "1")
    assert ok.returncode == 0, ok.stderr
    assert laspy.read(out).header.point_count == 1_000


def test_corrupt_and_truncated_las(tmp_path):
    garbage = tmp_path / "garbage.las"
    garbage.write_bytes(b"this is not a las file" * 100)
    assert_one_line_error(cli("run", str(garbage), "--ratio", "0.1"), "garbage.las")
    source = small_las(tmp_path / "in.las")
    truncated = tmp_path / "truncated.las"
    truncated.write_bytes(source.read_bytes()[:-5_000])
    out = tmp_path / "t.las"
    assert_one_line_error(cli("run", str(truncated), "--ratio", "0.1", "-o", str(out)), "truncated.las")
    assert not out.exists() and not list(tmp_path.glob(".t.las*"))


def test_lazrs_panic_is_one_line():
    result = cli("run", str(shared_file("edge-cases/simple-laszip-compressor-version-1.2r0.laz")), "--ratio", "0.1")
    assert_one_line_error(result, "simple-laszip-compressor-version-1.2r0.laz")


def test_zero_points(tmp_path):
    empty = tmp_path / "empty.las"
    laspy.LasData(laspy.LasHeader(version="1.2", point_format=1)).write(empty)
    assert_one_line_error(cli("run", str(empty), "--ratio", "0.1"), "no points")


def test_unknown_output_type_and_unwritable_folder(tmp_path):
    source = small_las(tmp_path / "in.las")
    assert_one_line_error(cli("run", str(source), "--ratio", "0.1", "-o", str(tmp_path / "o.txt")), "unsupported")
    assert_one_line_error(cli("run", str(source), "--ratio", "0.1", "-o", str(tmp_path / "no" / "o.las")),
                          "does not exist")
    assert_one_line_error(cli("run", str(source), "--ratio", "0.1", "-o", str(source / "o.las")),
                          "not a folder, so it cannot hold the output")


def test_config_preset_and_flags(tmp_path):
    source = small_las(tmp_path / "in.las")
    config = tmp_path / "mine.toml"
    config.write_text('[run]\nmethod = "random"\nworkers = 1\nbogus = 3\n')
    assert_one_line_error(cli("run", str(source), "--ratio", "0.1", "--config", str(config)), "bogus")
    config.write_text('[run]\nmethod = "random"\nworkers = 1\n')
    result = cli("run", str(source), "--ratio", "0.1", "--config", str(config), "-o", str(tmp_path / "o.laz"))
    assert result.returncode == 0, result.stderr
    assert "200 of 2,000 points" in result.stdout


def test_a_config_file_may_give_the_ratio(tmp_path):
    """--ratio (or --levels) is asked for unless the config file gives one ([run] ratio was a valid key that the
    CLI could not use)."""
    source = small_las(tmp_path / "in.las")
    config = tmp_path / "mine.toml"
    config.write_text('[run]\nmethod = "random"\nworkers = 1\nratio = 0.05\n')
    result = cli("run", str(source), "--config", str(config), "-o", str(tmp_path / "o.laz"))
    assert result.returncode == 0, result.stderr
    assert "100 of 2,000 points" in result.stdout
    assert_one_line_error(cli("run", str(source), "-o", str(tmp_path / "p.laz")), "give --ratio")


def test_demo_simulates_and_simplifies(tmp_path):
    result = cli("demo", "--out-dir", str(tmp_path), "--points", "40000", "--workers", "1")
    assert result.returncode == 0, result.stderr
    scan, simplified = laspy.read(tmp_path / "demo_street.laz"), laspy.read(tmp_path / "demo_street.simplified.laz")
    assert len(scan.points) == 40_000 and len(simplified.points) == 4_000
    assert np.isin(np.asarray(simplified.gps_time), np.asarray(scan.gps_time)).all()


def test_demo_checks_its_settings_first_and_simulates_again_for_another_size(tmp_path):
    """--points 0 or a bad --ratio is one line before any simulation (a traceback, or after simulating 1.5M
    points); a demo run with another --points simulates that size, one with the same reuses the scan."""
    assert_one_line_error(cli("demo", "--out-dir", str(tmp_path), "--points", "0"), "--points must be 1 or more")
    assert_one_line_error(cli("demo", "--out-dir", str(tmp_path), "--ratio", "2"), "--ratio must be in (0, 1]")
    assert not (tmp_path / "demo_street.laz").exists()
    for points, simulated in ((20_000, True), (30_000, True), (30_000, False)):
        result = cli("demo", "--out-dir", str(tmp_path), "--points", str(points), "--workers", "1")
        assert result.returncode == 0, result.stderr
        assert ("simulating" in result.stdout) == simulated and f"of {points:,} points" in result.stdout


def test_demo_flies_over_the_street_with_the_airborne_preset(tmp_path):
    """`--platform airborne` simulates the street from 80 m up and simplifies it with the airborne preset
    (100 m tiles: the whole 40k-point scan in one)."""
    result = cli("demo", "--out-dir", str(tmp_path), "--points", "40000", "--workers", "1", "--platform", "airborne")
    assert result.returncode == 0, result.stderr
    scan = laspy.read(tmp_path / "demo_airborne.laz")
    simplified = laspy.read(tmp_path / "demo_airborne.simplified.laz")
    assert len(scan.points) == 40_000 and len(simplified.points) == 4_000 and "(1 tiles" in result.stdout
    assert np.abs(np.asarray(scan.scan_angle_rank)).max() <= 25


def test_version_is_the_package_s_own_and_the_installed_metadata_agrees():
    """`pipeline --version` prints pipeline/version.py's value (the checkout's own, not whichever copy is
    installed), which pyproject.toml reads into the installed metadata."""
    from importlib.metadata import PackageNotFoundError, version

    from pipeline.version import __version__

    result = cli("--version")
    assert result.returncode == 0 and result.stdout.strip() == f"pipeline, version {__version__}", result
    try:
        assert version("lidar-simplify") == __version__
    except PackageNotFoundError:
        pytest.skip("lidar-simplify is not installed (run from a checkout on PYTHONPATH)")


def test_training_checks_its_data_and_replaces_no_weights_unasked(tmp_path):
    """The training commands wrote their weights over the package's own by default (their --out was the shipped
    weights' path, relative to where the command ran), replaced any file unasked, trained on an empty folder
    (and wrote untrained weights), and took --epochs 0 to a traceback. Each is now one line before any work."""
    empty, meshes = tmp_path / "empty", tmp_path / "meshes"
    empty.mkdir()
    meshes.mkdir()
    sphere = trimesh.creation.icosphere(subdivisions=2)
    for pose in ("ball0", "ball1"):
        sphere.export(meshes / f"{pose}.off")
    precious = tmp_path / "mine.pt"
    precious.write_bytes(b"PK my weights")
    for command, args, words in (
            ("train", ["--data", str(empty)], "no mesh files"),
            ("train-detail", ["--data", str(meshes), "--out", str(precious)], "already exists (pass --overwrite"),
            ("train", ["--data", str(meshes), "--out", str(precious)], "already exists (pass --overwrite"),
            ("train-detail", ["--data", str(meshes), "--out", str(tmp_path / "w.npz")], "the .pt file")):
        assert_one_line_error(cli(command, *args, cwd=tmp_path), *words.split(" (")[:1])
    assert precious.read_bytes() == b"PK my weights" and not (tmp_path / "tosca.pt").exists()
    sphere.export(empty / "ball0.off")  # one pose of its class: nothing left to train on
    assert_one_line_error(cli("train-detail", "--data", str(empty), cwd=tmp_path), "two poses or more")
    (meshes / "ball2.off.gz").write_bytes(b"\x1f\x8b\x08\x00 cut short")  # a truncated download
    assert_one_line_error(cli("train", "--data", str(meshes), cwd=tmp_path), "ball2.off.gz: not a readable mesh")
    bad = cli("train", "--data", str(meshes), "--epochs", "0", cwd=tmp_path)
    assert bad.returncode == 2 and "is not in the range x>=1" in bad.stderr and "Traceback" not in bad.stderr


def test_a_training_stopped_after_a_checkpoint_says_where_it_is(tmp_path):
    """A stop after the first checkpoint leaves a whole, part-trained .pt at --out (by design): the stop's line
    says so, where it said only 'interrupted'."""
    import signal
    import time

    meshes = tmp_path / "meshes"
    meshes.mkdir()
    for pose in ("ball0", "ball1"):
        trimesh.creation.icosphere(subdivisions=2).export(meshes / f"{pose}.off")
    out = tmp_path / "w.pt"
    run = subprocess.Popen([sys.executable, "-m", "pipeline.apps.cli", "train", "--data", str(meshes), "--out",
                            str(out), "--epochs", "1000", "--points", "64"], stderr=subprocess.PIPE, text=True)
    while not out.exists():
        assert run.poll() is None, run.stderr.read()
        time.sleep(0.05)
    run.send_signal(signal.SIGINT)
    _, stderr = run.communicate(timeout=120)
    assert run.returncode == 130 and stderr.strip().splitlines()[-1].startswith(f"pipeline: interrupted; {out} holds "
                                                                               "the last checkpoint")
