"""Bad input: one line `pipeline: error: FILE: problem`, exit 2, no traceback, nothing under the output name.

Odd but valid input runs and keeps exactly round(ratio * N) points. Full disks and read-only folders are
real: a tiny or read-only tmpfs mounted in a private user+mount namespace (skipped where unshare is refused).
"""
from __future__ import annotations

import math
import os
import shutil
import struct
import subprocess
import sys
from pathlib import Path

import laspy
import numpy as np
import pyproj
import pytest

from pipeline.errors import PipelineError
from pipeline.io.ply_source import PlySource
from tests.conftest import shared_file
from tests.test_cli import assert_one_line_error, cli

FAST = ("-m", "fps", "-w", "1", "-q")
EDGE_CASES = {  # file in shared/data/lidar/edge-cases -> None if it runs, else words its one-line error holds
    "epsg_4326.las": ("epsg_4326.las", "geographic", "--allow-geographic"),
    "fullwave.laz": None,
    "nocrs.las": None,
    "simple-laszip-compressor-version-1.2r0.laz": ("simple-laszip-compressor-version-1.2r0.laz", "cannot read"),
    "simple1_3.las": None,  # header bounds written unscaled: measured from the points instead
    "warsaw_small.las": None,
}
# LAS 1.0-1.3 public header: byte offset of a field and its struct format
VERSION_MAJOR, LEGACY_COUNT = (24, "<B"), (107, "<I")
X_SCALE, Y_SCALE, X_OFFSET, MAX_X, MIN_X = (131, "<d"), (139, "<d"), (155, "<d"), (179, "<d"), (187, "<d")


def make_las(path: Path, xyz: np.ndarray, scale: float = 0.01, crs: pyproj.CRS | None = None) -> Path:
    """A LAS 1.2 format 1 file (1.4 format 6 with a CRS, as a WKT VLR; LAZ by suffix), intensity = point number."""
    header = laspy.LasHeader(version="1.4" if crs else "1.2", point_format=6 if crs else 1)
    if crs is not None:
        header.add_crs(crs)
    header.scales, header.offsets = [scale] * 3, np.floor(xyz.min(axis=0, initial=0))
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz.T
    las.intensity = np.arange(len(xyz)) % 65_536
    las.write(path)
    return path


def scattered(n: int = 2_000, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0, 50, (n, 3)) * [1, 1, 0.1]


def patched(path: Path, field: tuple[int, str], value: float) -> Path:
    """The file with one header field overwritten in place."""
    data = bytearray(path.read_bytes())
    struct.pack_into(field[1], data, field[0], value)
    path.write_bytes(bytes(data))
    return path


def assert_nothing_written(output: Path) -> None:
    """Neither the output nor a temporary or scratch name beside it exists."""
    assert not output.exists()
    assert not [p.name for p in output.parent.glob(f".{output.name}*")]


def fails_cleanly(tmp_path: Path, inputs: list[Path], *words: str, args: tuple[str, ...] = ("--ratio", "0.1")) -> None:
    """The run fails with one line holding `words` and leaves nothing under its output name."""
    output = tmp_path / "out.laz"
    assert_one_line_error(cli("run", *map(str, inputs), *args, "-o", str(output), *FAST), *words)
    assert_nothing_written(output)


def runs_exactly(tmp_path: Path, source: Path, ratio: float, *args: str) -> laspy.LasData:
    """The run succeeds and its output holds exactly round(ratio * N) points."""
    output = tmp_path / "out.las"
    result = cli("run", str(source), "--ratio", str(ratio), "-o", str(output), *FAST, *args)
    assert result.returncode == 0, result.stderr
    count = laspy.open(source).header.point_count
    simplified = laspy.read(output)
    assert len(simplified.points) == round(ratio * count)
    return simplified


def test_every_edge_case_file_is_classified():
    folder = shared_file("edge-cases")
    assert sorted(p.name for p in folder.iterdir()) == sorted(EDGE_CASES)


@pytest.mark.parametrize("name", sorted(EDGE_CASES))
def test_edge_case_file_runs_or_fails_in_one_line(tmp_path, name):
    source = shared_file(f"edge-cases/{name}")
    if EDGE_CASES[name] is None:
        runs_exactly(tmp_path, source, 0.1)
    else:
        fails_cleanly(tmp_path, [source], *EDGE_CASES[name])


@pytest.mark.parametrize("suffix, points", [(".las", 20_000), (".laz", 20_000), (".laz", 130_000)],
                         ids=["las", "laz-one-chunk", "laz-three-chunks"])
def test_truncated_file(tmp_path, suffix, points):
    """Also a LAZ file of several chunks, whose pieces are decoded through the chunk table: cut short, it
    has none where its header points, and the read falls back to seeking, which reports the truncation."""
    source = make_las(tmp_path / f"whole{suffix}", scattered(points))
    truncated = tmp_path / f"half{suffix}"
    truncated.write_bytes(source.read_bytes()[: source.stat().st_size // 2])
    fails_cleanly(tmp_path, [truncated], truncated.name, "header says" if suffix == ".las" else "truncated")


@pytest.mark.parametrize("suffix, points, claimed", [(".las", 3_000, 5_000), (".laz", 3_000, 5_000),
                                                     (".laz", 130_000, 140_000), (".laz", 130_000, 200_000)],
                         ids=["las", "laz-one-chunk", "laz-last-chunk-short", "laz-chunks-missing"])
def test_header_count_larger_than_the_data(tmp_path, suffix, points, claimed):
    """LAS is caught from the file size; LAZ only when a task decodes past the data: in the last chunk the
    table lists (lazrs asked for more points than it holds) or past the table's end."""
    source = patched(make_las(tmp_path / f"in{suffix}", scattered(points)), LEGACY_COUNT, claimed)
    fails_cleanly(tmp_path, [source], source.name, "header says" if suffix == ".las" else "cannot read")


def test_header_bounds_missing_every_point_are_measured(tmp_path):
    """Bounds that miss even the first points (as if written unscaled) are replaced by one streamed pass."""
    source = patched(patched(make_las(tmp_path / "in.las", scattered()), MIN_X, 1e6), MAX_X, 1e6 + 50)
    runs_exactly(tmp_path, source, 0.1)


def test_points_straying_outside_header_bounds_later(tmp_path):
    """The first points fit the header, later ones do not: the Dask worker reading them fails in one line."""
    xyz = scattered(3_000)
    xyz[:1_500, 0] /= 5
    source = patched(make_las(tmp_path / "in.las", xyz), MAX_X, 10.0)
    fails_cleanly(tmp_path, [source], "in.las", "outside the header's bounds", "lasinfo -repair_bb")


@pytest.mark.parametrize("field, value, words", [
    (X_SCALE, math.nan, "scale"), (Y_SCALE, math.inf, "scale"), (X_SCALE, 0.0, "scale"),
    (X_OFFSET, -math.inf, "offset"), (MAX_X, math.nan, "bounds"),
    (X_SCALE, 1e306, "overflows"),  # finite, but X * scale would be inf
    (VERSION_MAJOR, 9, "LAS version 9.2"),
], ids=["scale-nan", "scale-inf", "scale-zero", "offset-inf", "bounds-nan", "scale-overflows", "version-9"])
def test_corrupt_header_values(tmp_path, field, value, words):
    source = patched(make_las(tmp_path / "in.las", scattered()), field, value)
    fails_cleanly(tmp_path, [source], "in.las", words)


def write_ply(path: Path, xyz: np.ndarray) -> Path:
    header = f"ply\nformat binary_little_endian 1.0\nelement vertex {len(xyz)}\n"
    header += "".join(f"property double {axis}\n" for axis in "xyz") + "end_header\n"
    path.write_bytes(header.encode() + np.ascontiguousarray(xyz, dtype="<f8").tobytes())
    return path


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
def test_non_finite_ply_coordinates(tmp_path, value):
    xyz = scattered(100)
    xyz[37, 1] = value
    source = write_ply(tmp_path / "in.ply", xyz)
    fails_cleanly(tmp_path, [source], "in.ply", "NaN or infinite y coordinate at vertex 37 ")


def test_a_non_finite_ply_coordinate_is_named_by_its_vertex_past_the_first_chunk(tmp_path):
    xyz = scattered(2_000)
    xyz[1_537, 2] = math.nan
    with pytest.raises(PipelineError, match="NaN or infinite z coordinate at vertex 1537 "):
        PlySource(write_ply(tmp_path / "in.ply", xyz), chunk=500)


def test_a_ply_too_wide_for_the_millimetre_grid(tmp_path):
    """3,000 km along x does not fit LAS's 32-bit integers at 1 mm steps: said before any point is read."""
    xyz = scattered(100)
    xyz[5, 0] += 3e6
    fails_cleanly(tmp_path, [write_ply(tmp_path / "in.ply", xyz)], "in.ply", "32-bit grid")


@pytest.mark.parametrize("suffix", [".laz", ".ply"])
def test_zero_points(tmp_path, suffix):
    source = tmp_path / f"empty{suffix}"
    write_ply(source, np.empty((0, 3))) if suffix == ".ply" else make_las(source, np.zeros((0, 3)) + 1)
    fails_cleanly(tmp_path, [source], source.name, "no points")


@pytest.mark.parametrize("method", ["fps", "random", "voxel", "tcp"])
def test_all_points_identical(tmp_path, method):
    """One position 1,000 times: exactly round(r * N) points come out, each a different source record."""
    source = make_las(tmp_path / "same.las", np.tile([[10.0, 20.0, 1.0]], (1_000, 1)))
    simplified = runs_exactly(tmp_path, source, 0.1, "-m", method)
    assert len(np.unique(simplified.intensity)) == 100
    np.testing.assert_allclose(simplified.xyz, [[10.0, 20.0, 1.0]] * 100)


@pytest.mark.parametrize("ratio, words", [("inf", "ratio"), ("-inf", "ratio"), ("1e-9", "keeps 0")])
def test_ratio_beyond_test_cli(tmp_path, ratio, words):
    """0, 1.5, nan and -0.1 are in test_cli; these are the remaining ways a ratio can be wrong."""
    fails_cleanly(tmp_path, [make_las(tmp_path / "in.las", scattered())], words, args=("--ratio", ratio))


def test_missing_second_input(tmp_path):
    fails_cleanly(tmp_path, [make_las(tmp_path / "in.las", scattered()), tmp_path / "gone.laz"], "gone.laz",
                  "no such file")


@pytest.mark.parametrize("name", ["tiles", "tiles.las"])
def test_folder_as_input(tmp_path, name):
    (tmp_path / name).mkdir()
    fails_cleanly(tmp_path, [tmp_path / name], name, "is a folder")


def test_a_zarr_store_as_input_is_named_as_one(tmp_path):
    (tmp_path / "small.zarr").mkdir()
    fails_cleanly(tmp_path, [tmp_path / "small.zarr"], "small.zarr", "is a zarr store", "pipeline eval")


def test_device_as_input(tmp_path):
    fails_cleanly(tmp_path, [Path("/dev/null")], "/dev/null", "not a regular file")


@pytest.mark.parametrize("content, words", [
    (b"", "not a LAS/LAZ file"),
    (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1\n", "not a LAS/LAZ file"),
    (b"\x89PNG\r\n\x1a\n" + bytes(400), "not a LAS/LAZ file"),
    (b"LASF" + bytes(50), "cut short"),
    (b"LASF" + bytes(range(256)) * 2, "LAS version 20.21"),
    (b"LASF" + bytes(20) + b"\x01\x02" + bytes(range(256)) * 2, "VLRs"),  # laspy would read them past the end
], ids=["empty", "ply", "png", "lasf-short", "lasf-garbage", "lasf-1.2-garbage"])
def test_not_las_named_las(tmp_path, content, words):
    source = tmp_path / "fake.las"
    source.write_bytes(content)
    fails_cleanly(tmp_path, [source], "fake.las", words)


def test_laz_named_las_runs(tmp_path):
    """Compression is told by the header, not the name: a LAZ file called .las is read as LAZ."""
    source = tmp_path / "really-laz.las"
    make_las(tmp_path / "in.laz", scattered()).rename(source)
    runs_exactly(tmp_path, source, 0.25)


def test_output_under_a_regular_file(tmp_path):
    source = make_las(tmp_path / "in.las", scattered())
    assert_one_line_error(cli("run", str(source), "--ratio", "0.1", "-o", "/dev/null/out.las", *FAST), "/dev/null")


def test_read_only_output_folder_by_permissions(tmp_path):
    source = make_las(tmp_path / "in.las", scattered())
    folder = tmp_path / "locked"
    folder.mkdir()
    folder.chmod(0o555)
    try:
        if os.access(folder, os.W_OK):
            pytest.skip("running as root: permissions do not stop writes (the read-only mount test covers this)")
        fails_cleanly(folder, [source], "not writable")
    finally:
        folder.chmod(0o755)


def test_existing_zarr_output_needs_overwrite(tmp_path):
    output = tmp_path / "out.zarr"
    output.mkdir()
    (output / "keep").write_text("mine")
    result = cli("run", str(make_las(tmp_path / "in.las", scattered())), "--ratio", "0.1", "-o", str(output), *FAST)
    assert_one_line_error(result, "out.zarr", "already exists")
    assert [p.name for p in output.iterdir()] == ["keep"]


def in_private_mount(mount: Path, options: str, *args: str) -> subprocess.CompletedProcess:
    """`pipeline ARGS` with a tmpfs (mount options given) on `mount`, seen only by that command; its stdout
    ends with what the mount holds afterwards, one name a line."""
    if shutil.which("unshare") is None or subprocess.run(["unshare", "-Urm", "true"], capture_output=True).returncode:
        pytest.skip("unshare -Urm (a private user+mount namespace) is not allowed here")
    mount.mkdir(exist_ok=True)
    script = 'mount -t tmpfs -o "$1" tmpfs "$2" || exit 99; mount=$2; shift 2; "$@"; rc=$?; ls -A "$MNT"; exit $rc'
    return subprocess.run(["unshare", "-Urm", "sh", "-c", script, "sh", options, str(mount),
                           sys.executable, "-m", "pipeline.apps.cli", *args], capture_output=True, text=True,
                          env={**os.environ, "MNT": str(mount)}, timeout=600)


@pytest.mark.parametrize("suffix", [".las", ".laz", ".zarr"])
def test_full_disk_at_output(tmp_path, suffix):
    """Scratch fits, the output does not: the error names the output and says so; nothing is left there."""
    source = make_las(tmp_path / "in.las", scattered(30_000))
    output = tmp_path / "full" / f"out{suffix}"
    result = in_private_mount(output.parent, "size=64k", "run", str(source), "--ratio", "0.9", "-o", str(output),
                              "--scratch", str(tmp_path), *FAST)
    assert_one_line_error(result, str(output), "No space left")
    assert result.stdout == ""  # the mount is empty afterwards
    assert all(".work-" in p.name for p in tmp_path.glob(".out*"))  # only the finished tiles, kept to resume
    assert "re-run the same command to resume" in result.stderr


def test_no_room_for_the_copc_spill_is_refused_before_any_work(tmp_path):
    """COPC spills the kept records beside the output before compressing them node by node: a disk without
    room for that is refused up front, with nothing written and no work folder left."""
    source = make_las(tmp_path / "in.las", scattered(30_000))
    output = tmp_path / "full" / "out.copc.laz"
    result = in_private_mount(output.parent, "size=64k", "run", str(source), "--ratio", "0.9", "-o", str(output),
                              "--scratch", str(tmp_path), *FAST)
    assert_one_line_error(result, str(output.parent), "not enough space left", "COPC")
    assert result.stdout == ""
    assert not list(tmp_path.glob(".out*"))


def test_full_disk_at_scratch(tmp_path):
    """Scratch space is checked before any work: the bucketed scan needs every record, uncompressed."""
    source = make_las(tmp_path / "in.las", scattered(30_000))
    scratch = tmp_path / "scratch"
    result = in_private_mount(scratch, "size=64k", "run", str(source), "--ratio", "0.5", "-o",
                              str(tmp_path / "out.las"), "--scratch", str(scratch), *FAST)
    assert_one_line_error(result, str(scratch), "not enough space left", "--scratch")
    assert result.stdout == ""
    assert_nothing_written(tmp_path / "out.las")


def test_missing_scratch_folder(tmp_path):
    source = make_las(tmp_path / "in.las", scattered())
    fails_cleanly(tmp_path, [source], str(tmp_path / "nowhere"), "does not exist",
                  args=("--ratio", "0.1", "--scratch", str(tmp_path / "nowhere")))


def test_read_only_output_folder(tmp_path):
    source = make_las(tmp_path / "in.las", scattered())
    output = tmp_path / "ro" / "out.las"
    result = in_private_mount(output.parent, "ro", "run", str(source), "--ratio", "0.1", "-o", str(output), *FAST)
    assert_one_line_error(result, str(output.parent), "not writable")


def test_laz_pieces_are_the_files_points_within_and_across_chunks(tmp_path):
    """Pieces of more than one chunk are decoded through the chunk table (chunks in parallel), others by
    seeking; laspy's own reading of the whole file is the reference, the last chunk's part included."""
    from pipeline.io.las_source import LasSource, spans_chunks

    path = make_las(tmp_path / "in.laz", scattered(130_000))  # chunks of 50,000: the last holds 30,000
    whole = laspy.read(path).points.array
    source = LasSource(path)
    pieces = ((0, 130_000), (0, 5), (49_990, 20), (10, 60_000), (99_999, 30_001), (129_990, 10), (50_000, 50_000))
    assert [spans_chunks(source.header, *piece) for piece in pieces] == [True, False, True, True, True, False, False]
    for start, count in pieces:
        np.testing.assert_array_equal(source.read(start, count), whole[start:start + count])


class PanicException(BaseException):
    """Stands in for pyo3's PanicException (a BaseException), whose class cannot be imported."""


@pytest.mark.parametrize("raised, expected", [(PanicException("index out of bounds\nstack backtrace:"), PipelineError),
                                              (KeyboardInterrupt(), KeyboardInterrupt)], ids=["panic", "ctrl-c"])
def test_lazrs_panic_names_the_file(tmp_path, monkeypatch, raised, expected):
    """A panic while reading the header or points becomes one line naming the file; Ctrl-C stays Ctrl-C."""
    from pipeline.io import las_source
    source = make_las(tmp_path / "in.laz", scattered())
    reader = las_source.LasSource(source)

    def broken(path: Path) -> laspy.LasReader:
        raise raised

    monkeypatch.setattr(las_source, "open_las", broken)
    with pytest.raises(expected) as opening:
        las_source.LasSource(source)
    with pytest.raises(expected) as reading:
        reader.read(0, 10)
    if expected is PipelineError:
        for caught in (opening, reading):
            assert str(caught.value) == (f"{source}: cannot read LAS/LAZ data (corrupt, truncated or unsupported "
                                         "file?): index out of bounds")


def test_multi_line_messages_become_one():
    assert str(PipelineError("a.las: failed\n  at line 3\n\n")) == "a.las: failed; at line 3"


def geographic_points() -> np.ndarray:
    rng = np.random.default_rng(1)
    return np.column_stack([rng.uniform(-94.70, -94.66, 2_000), rng.uniform(31.03, 31.05, 2_000),
                            rng.uniform(40, 80, 2_000)])


def test_geographic_crs_is_refused_unless_allowed(tmp_path):
    source = make_las(tmp_path / "wgs84.las", geographic_points(), scale=1e-7, crs=pyproj.CRS.from_epsg(4326))
    fails_cleanly(tmp_path, [source], "wgs84.las", "geographic", "reproject", "--allow-geographic")
    runs_exactly(tmp_path, source, 0.1, "--allow-geographic")


def test_degree_like_coordinates_without_crs_are_refused(tmp_path):
    source = make_las(tmp_path / "lonlat.las", geographic_points(), scale=1e-7)
    fails_cleanly(tmp_path, [source], "lonlat.las", "look like degrees", "--allow-geographic")


def test_projected_crs_runs(tmp_path):
    """Metres in a small range (a local grid, UTM near its origin) are not mistaken for degrees."""
    source = make_las(tmp_path / "utm.las", scattered(), crs=pyproj.CRS.from_epsg(32633))
    runs_exactly(tmp_path, source, 0.1)


@pytest.mark.parametrize("args, words", [(("--tile-size", "0"), "--tile-size must be a positive number of metres"),
                                         (("--overlap", "-1"), "--overlap must be 0 or more metres"),
                                         (("--seam-tolerance", "-0.5"), "--seam-tolerance must be 0 or more metres")])
def test_lengths_out_of_range_say_what_is_allowed(tmp_path, args, words):
    """An overlap or seam tolerance of 0 is allowed (it runs): the message says so, not 'a positive number'."""
    fails_cleanly(tmp_path, [make_las(tmp_path / "in.las", scattered())], words, args=("--ratio", "0.1", *args))
