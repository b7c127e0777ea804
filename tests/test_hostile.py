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
from tests.test_faults import ON_A_CLUSTER

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


def patched_bytes(path: Path, offset: int, value: int, size: int) -> Path:
    """The file with one little-endian header field overwritten."""
    path.write_bytes(bytes(patched_bytes_in(bytearray(path.read_bytes()), offset, value, size)))
    return path


@pytest.mark.parametrize("command", ["run", "info"])
def test_point_data_offset_inside_the_vlrs_is_refused(tmp_path, scan, command):
    """LAS 1.4 format 6 with a CRS VLR: a point offset moved back into that VLR would read VLR bytes as points."""
    import pyproj

    from tests.test_bad_input import make_las, scattered

    source = make_las(tmp_path / "crs.las", scattered(), crs=pyproj.CRS.from_epsg(32617))
    header_size = laspy.read(source).header.offset_to_point_data
    patched_bytes(source, 96, header_size - 100, 4)
    args = ("run", str(source), "-r", "0.1", "-o", "out.las", *FAST) if command == "run" else ("info", str(source))
    refused(tmp_path, args, [source], "runs past the start of the point data")


@pytest.mark.parametrize("command", ["run", "info"])
def test_billions_of_evlrs_are_refused_at_once(tmp_path, command):
    import pyproj

    from tests.test_bad_input import make_las, scattered

    source = make_las(tmp_path / "evlr.las", scattered(), crs=pyproj.CRS.from_epsg(32617))
    patched_bytes(source, 235, source.stat().st_size, 8)  # first EVLR at the file's end ...
    patched_bytes(source, 243, 3_000_000_000, 4)           # ... and three billion of them
    args = ("run", str(source), "-r", "0.1", "-o", "out.las", *FAST) if command == "run" else ("info", str(source))
    refused(tmp_path, args, [source], "3,000,000,000 EVLRs")


@pytest.mark.parametrize("config, words", [
    ("run = 3\n", "[run] must be a table"),
    ("[run]\nratio = true\n", "[run]: ratio must be a number"),
    ("[run]\nworkers = 1.5\n", "[run]: workers must be a whole number"),
    ("[run]\nmethod = 4\n", "[run]: method must be a string"),
    ("[run]\ntiles = 4\n", "unknown setting(s) tiles"),
    ("in_process_points = 0\n[run]\nworkers = 2\n", "'in_process_points' is outside [run]"),
])
def test_config_file_errors_name_the_file_and_key(tmp_path, scan, config, words):
    settings = tmp_path / "settings.toml"
    settings.write_text(config)
    refused(tmp_path, ("run", str(scan), "-r", "0.1", "-o", "out.las", "-c", str(settings)), [scan, settings],
            "settings.toml", words)


@pytest.mark.parametrize("jobs, words", [
    ('[[job]]\ninput = ""\n', "job 1 input must be a non-empty path"),
    ("[[job]]\ninput = 5\n", "job 1: input must be a path or a list of paths"),
    ("[[job]]\ninput = []\n", "job 1: input must be a path or a list of paths"),
    ("job = 3\n", "jobs must be [[job]] tables"),
    ('defaults = "fast"\n[[job]]\ninput = "in.las"\n', "[defaults] must be a table"),
    ('[defaults]\nratio = "0.1"\n[[job]]\ninput = "in.las"\n', "[defaults]: ratio must be a number"),
    ('[[job]]\ninput = "in.las"\nseed = "x"\n', "job 1: seed must be a whole number"),
])
def test_batch_job_list_errors_name_the_file_and_entry(tmp_path, scan, jobs, words):
    job_list = tmp_path / "jobs.toml"
    job_list.write_text(jobs)
    out = tmp_path / "out"
    out.mkdir()
    refused(tmp_path, ("batch", str(job_list), "--out-dir", str(out), "-r", "0.1"), [scan, job_list, out],
            "jobs.toml", words)


def test_batch_manifest_that_is_not_ours_is_refused(tmp_path, scan):
    manifest = tmp_path / "list.json"
    manifest.write_text("[1, 2]")
    scans = tmp_path / "scans"
    scans.mkdir()
    os.link(scan, scans / "in.las")
    refused(tmp_path, ("batch", str(scans), "--out-dir", str(tmp_path / "out"), "-r", "0.1", "--manifest",
                       str(manifest)), [scan, manifest], "not a batch manifest")


def test_memory_limit_too_small_to_start_a_worker_is_refused(tmp_path, scan):
    refused(tmp_path, ("run", str(scan), "-r", "0.1", "-o", "out.las", "--memory-limit", "40MB", *FAST), [scan],
            "--memory-limit 40MB is below")


@pytest.mark.parametrize("service", ["silent", "http"])
def test_scheduler_address_of_another_service_fails_in_bounded_time(tmp_path, scan, service):
    """Something listens but never speaks Dask: silence (Dask's client waited for ever) or HTTP (it tried to
    allocate 3 EiB)."""
    import socket
    import threading

    listener = socket.create_server(("127.0.0.1", 0))
    port = listener.getsockname()[1]
    accepted: list[socket.socket] = []

    def serve() -> None:
        while True:
            try:
                connection, _ = listener.accept()
            except OSError:
                return
            accepted.append(connection)
            if service == "http":
                connection.recv(1024)
                connection.sendall(b"HTTP/1.1 200 OK\r\nContent-Length: 2\r\n\r\nhi")

    threading.Thread(target=serve, daemon=True).start()
    try:
        refused(tmp_path, ("run", str(scan), "-r", "0.1", "-o", "out.las", "--scheduler", f"tcp://127.0.0.1:{port}",
                           *FAST), [scan], f"127.0.0.1:{port}", "Dask")
    finally:
        listener.close()
        for connection in accepted:
            connection.close()


def test_more_workers_than_cores_are_capped_with_a_note(tmp_path, scan):
    result = cli("run", str(scan), "-r", "0.1", "-o", str(tmp_path / "out.las"), "-m", "fps", "-w", "1000")
    assert result.returncode == 0, result.stderr
    assert "--workers 1000 capped at" in result.stderr and "Traceback" not in result.stderr


@pytest.mark.parametrize("second_crs, words", [(32618, "EPSG:32618"), (None, "no CRS")])
def test_inputs_in_different_crss_are_refused(tmp_path, second_crs, words):
    import pyproj

    from tests.test_bad_input import make_las, scattered

    first = make_las(tmp_path / "utm17.las", scattered(), crs=pyproj.CRS.from_epsg(32617))
    second = (make_las(tmp_path / "other.las", scattered(seed=1), crs=pyproj.CRS.from_epsg(second_crs)) if second_crs
              else small_las(tmp_path / "other.las"))  # the same point format 6, without a CRS
    refused(tmp_path, ("run", str(first), str(second), "-r", "0.1", "-o", "out.las", *FAST), [first, second],
            "differs from", "EPSG:32617", words)


def test_inputs_in_one_crs_are_merged(tmp_path):
    import pyproj

    from tests.test_bad_input import make_las, scattered

    parts = [make_las(tmp_path / f"p{i}.las", scattered(seed=i), crs=pyproj.CRS.from_epsg(32617)) for i in range(2)]
    result = cli("run", *map(str, parts), "-r", "0.1", "-o", str(tmp_path / "out.las"), *FAST)
    assert result.returncode == 0, result.stderr
    assert laspy.read(tmp_path / "out.las").header.point_count == 400


def test_header_bounds_near_float_max_are_measured_from_the_points(tmp_path):
    """Bounds no scale and offset can reach (1.7e308) are not the points': measured instead, exact count."""
    from tests.test_bad_input import MAX_X, MIN_X, make_las, patched, scattered

    source = patched(patched(make_las(tmp_path / "huge.las", scattered()), MAX_X, 1.7e308), MIN_X, -1.7e308)
    result = cli("run", str(source), "-r", "0.1", "-o", str(tmp_path / "out.las"), *FAST)
    assert result.returncode == 0, result.stderr
    assert laspy.read(tmp_path / "out.las").header.point_count == 200


def test_corrupt_laz_chunk_count_is_refused_not_an_abort(tmp_path):
    """A chunk table claiming 2^31 chunks made lazrs abort the process (exit -6, no message)."""
    from tests.test_bad_input import make_las, scattered

    source = make_las(tmp_path / "in.laz", scattered(20_000))
    with laspy.open(source) as reader:
        point_offset = reader.header.offset_to_point_data
    data = bytearray(source.read_bytes())
    table = int.from_bytes(data[point_offset:point_offset + 8], "little")
    source.write_bytes(bytes(patched_bytes_in(data, table + 4, 2**31, 4)))
    refused(tmp_path, ("run", str(source), "-r", "0.1", "-o", "out.las", *FAST), [source], "chunk table lists")


def patched_bytes_in(data: bytearray, offset: int, value: int, size: int) -> bytearray:
    """The bytes with one little-endian field overwritten."""
    data[offset:offset + size] = value.to_bytes(size, "little")
    return data


def test_workers_dying_of_memory_end_in_one_line_that_names_the_limit(tmp_path):
    """256 MiB passes the floor, but a worker that loads torch for the paper's network and runs it on 100k points
    holds more: Dask kills it at 95 % of its limit, again on each retry; the run ends instead of restarting it for
    ever, and the rerun with more memory resumes (the limit is not part of the work folder's key). The worker
    must stay over the limit for several of the nanny's 100 ms memory checks: on 2,000 points it sat at the
    limit and passed one run in two; on 20k it was over it for about 0.2 s of each try, and one run in three
    finished (rc 0, a CI failure); on 100k, 0.8 s."""
    scan = small_las(tmp_path / "in.las", n=100_000)
    args = ("run", str(scan), "-r", "0.1", "-m", "paper", "-o", str(tmp_path / "out.laz"), "-w", "1", "-q",
            "--config", str(ON_A_CLUSTER))
    result = cli(*args, "--memory-limit", "256MiB")
    assert_one_line_error(result, "died again and again", "--memory-limit")
    assert not (tmp_path / "out.laz").exists()
    again = cli(*args, "--memory-limit", "2GB")
    assert again.returncode == 0, again.stderr
    assert laspy.read(tmp_path / "out.laz").header.point_count == 10_000


def test_a_second_run_of_the_same_command_while_the_first_runs_is_refused_in_one_line(tmp_path):
    """Overlapping scheduled jobs ran the same command into one work folder: the second failed on a file the
    first renamed (a FileNotFoundError traceback), or both finished and the second replaced the output. The
    first run holds the folder (here the test holds it, as a running `pipeline run` does): the second is
    refused before it touches the folder or the output, and runs once the folder is free."""
    from pipeline.config import build_config
    from pipeline.engine.workdir import WorkDir

    scan, out = small_las(tmp_path / "in.las", n=5_000), tmp_path / "out.las"
    work = WorkDir.for_run(out, None, [scan], build_config(None, ratio=0.1, method="fps", workers=1).in_unit(1.0))
    args = ("run", str(scan), "-r", "0.1", "-o", str(out), *FAST)
    with work.held():
        assert_one_line_error(cli(*args), "another run of the same command", str(work.path))
        assert not out.exists() and (work.path / "manifest.json").is_file()
    result = cli(*args)
    assert result.returncode == 0, result.stderr
    assert laspy.read(out).header.point_count == 500 and not work.path.exists()
