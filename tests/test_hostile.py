"""A hostile user's outputs: no command ever replaces, deletes or rereads an input, nor a file or folder
that is not an output of its own kind, whatever `--overwrite` says.

Every refusal is the README's promise: one line, exit 2, no traceback, nothing new under the output
name, and every input and bystander byte-identical (hashed before and after).
"""
from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import laspy
import numpy as np
import pytest
import trimesh

from tests.test_cli import assert_one_line_error, cli, small_las

FAST = ("-m", "fps", "-w", "1", "-q")


def fingerprint(*paths: Path) -> dict[str, str]:
    """SHA-256 of every file under the paths (a folder: each file in it), keyed by path."""
    files = [f for p in paths for f in ([p] if p.is_file() else sorted(p.rglob("*")))]
    return {str(f): hashlib.sha256(f.read_bytes()).hexdigest() for f in files if f.is_file()}


def refused(tmp_path: Path, args: tuple[str, ...], guarded: list[Path], *words: str) -> None:
    """The command fails in one line with `words`, and nothing it was given or pointed at changed."""
    before = fingerprint(*guarded)
    listing = sorted(os.listdir(tmp_path))
    assert_one_line_error(cli(*args, cwd=tmp_path), *words)
    assert fingerprint(*guarded) == before
    assert sorted(os.listdir(tmp_path)) == listing  # no work folder, temporary or output left behind


@pytest.fixture()
def scan(tmp_path: Path) -> Path:
    return small_las(tmp_path / "in.las")


def test_output_that_is_the_input_is_refused_even_with_overwrite(tmp_path, scan):
    refused(tmp_path, ("run", str(scan), "-r", "0.1", "-o", str(scan), "--overwrite", *FAST), [scan],
            "is also an input", "in.las")


def test_output_that_is_the_second_input_is_refused(tmp_path, scan):
    second = small_las(tmp_path / "second.las", n=500)
    refused(tmp_path, ("run", str(scan), str(second), "-r", "0.1", "-o", str(second), "--overwrite", *FAST),
            [scan, second], "is also an input")


def test_output_spelled_differently_is_still_the_input(tmp_path, scan):
    (tmp_path / "sub").mkdir()
    spelled = f"{tmp_path}/sub/../in.las"
    refused(tmp_path, ("run", "in.las", "-r", "0.1", "-o", spelled, "--overwrite", *FAST), [scan], "is also an input")


@pytest.mark.parametrize("link", [os.symlink, os.link])
def test_output_linked_to_the_input_is_refused(tmp_path, scan, link):
    link(scan, tmp_path / "alias.las")
    refused(tmp_path, ("run", str(scan), "-r", "0.1", "-o", "alias.las", "--overwrite", *FAST), [scan],
            "is also an input")


@pytest.mark.parametrize("name", ["out.laz", "out.las", "photos.zarr"])
def test_overwrite_never_deletes_a_folder_that_is_not_our_output(tmp_path, scan, name):
    folder = tmp_path / name
    folder.mkdir()
    (folder / "holiday.jpg").write_bytes(b"\xff\xd8 not a point cloud")
    refused(tmp_path, ("run", str(scan), "-r", "0.1", "-o", str(folder), "--overwrite", *FAST), [scan, folder],
            "refusing to replace it")


@pytest.mark.parametrize("name", ["notes.laz", "data.zarr"])
def test_overwrite_never_replaces_a_file_of_another_kind(tmp_path, scan, name):
    stranger = tmp_path / name
    stranger.write_text("minutes of the survey meeting\n")
    refused(tmp_path, ("run", str(scan), "-r", "0.1", "-o", str(stranger), "--overwrite", *FAST), [scan, stranger],
            "refusing to replace it")


def test_overwrite_replaces_an_output_of_its_own_kind(tmp_path, scan):
    out = tmp_path / "out.laz"
    for _ in range(2):
        result = cli("run", str(scan), "-r", "0.1", "-o", str(out), "--overwrite", *FAST)
        assert result.returncode == 0, result.stderr
    assert laspy.read(out).header.point_count == 200


def test_zarr_output_holding_an_input_is_refused(tmp_path):
    store = tmp_path / "old.zarr"
    inner = small_las(tmp_path / "in.las")
    assert cli("run", str(inner), "-r", "0.5", "-o", str(store), *FAST).returncode == 0
    moved = store / "in.las"
    inner.rename(moved)
    refused(tmp_path, ("run", str(moved), "-r", "0.1", "-o", str(store), "--overwrite", *FAST), [store],
            "holds the input")


@pytest.mark.parametrize("spelling", ["same", "symlink"])
def test_the_same_file_twice_is_refused(tmp_path, scan, spelling):
    second = scan
    if spelling == "symlink":
        second = tmp_path / "again.las"
        os.symlink(scan, second)
    refused(tmp_path, ("run", str(scan), str(second), "-r", "0.1", "-o", "out.laz", *FAST), [scan], "given twice")


def test_batch_with_colliding_outputs_is_refused_before_any_work(tmp_path):
    """a.laz and a.ply both default to a.simplified.laz: refused before either (or b.las) runs."""
    scans, out = tmp_path / "scans", tmp_path / "out"
    scans.mkdir(), out.mkdir()
    las = laspy.read(small_las(scans / "b.las"))
    las.write(scans / "a.laz")
    trimesh.PointCloud(np.column_stack([las.x, las.y, las.z])).export(scans / "a.ply")
    refused(tmp_path, ("batch", str(scans), "--out-dir", str(out), "-r", "0.1", *FAST[:4]), [scans, out],
            "written by two jobs", "a.simplified.laz")


def test_batch_into_its_own_scan_folder_never_reads_its_outputs(tmp_path):
    scans = tmp_path / "scans"
    scans.mkdir()
    small_las(scans / "a.las")
    small_las(scans / "b.las", n=1_000)
    for run in range(2):
        result = cli("batch", str(scans), "--out-dir", str(scans), "-r", "0.1", *FAST[:4], "--log-json")
        assert result.returncode == 0, result.stderr
        events = [json.loads(line) for line in result.stdout.splitlines()]
        inputs = {Path(e["input"][0]).name for e in events if e["event"] in ("started", "skipped")}
        assert inputs == {"a.las", "b.las"}, events
    assert sorted(p.name for p in scans.glob("*.las")) == ["a.las", "a.simplified.las", "b.las", "b.simplified.las"]


def test_batch_job_writing_over_another_jobs_input_is_refused(tmp_path):
    first, second = small_las(tmp_path / "one.las"), small_las(tmp_path / "two.las", n=1_000)
    jobs = tmp_path / "jobs.toml"
    jobs.write_text('[defaults]\nratio = 0.1\nmethod = "fps"\n'
                    '[[job]]\ninput = "one.las"\noutput = "two.las"\n'
                    '[[job]]\ninput = "two.las"\noutput = "two-small.las"\n')
    refused(tmp_path, ("batch", str(jobs), "--overwrite"), [first, second, jobs], "is also an input")


def test_mesh_output_that_is_the_input_is_refused(tmp_path):
    mesh = tmp_path / "ball.ply"
    trimesh.creation.icosphere(subdivisions=3).export(mesh)
    refused(tmp_path, ("run", str(mesh), "--mesh", "-r", "0.5", "-o", str(mesh), "--overwrite", "-q"), [mesh],
            "is also an input")
