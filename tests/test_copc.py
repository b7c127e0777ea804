"""The COPC output (`-o X.copc.laz`), read back by laspy's CopcReader and by copclib (and PDAL when installed)."""
from __future__ import annotations

import json
import shutil
import struct
import subprocess
from pathlib import Path

import copclib
import laspy
import numpy as np
import pyproj
import pytest
from click.testing import CliRunner
from laspy.copc import Bounds
from laspy.vlrs.known import ExtraBytesVlr, GeoKeyDirectoryVlr

import pipeline
from pipeline.apps.cli import cli
from pipeline.errors import PipelineError
from pipeline.io import copc_output
from pipeline.io.crs import crs_wkt, las_wkt
from pipeline.io.las_source import LasSource, variable_chunks
from pipeline.io.output_meta import OutputMeta
from pipeline.io.provenance import read_provenance
from pipeline.io.writers import write_output
from pipeline.simulate.writing import street_header
from tests.conftest import shared_file, simulated_street
from tests.test_formats import random_scan
from tiling.assemble import TilePart

RUN = dict(ratio=0.5, method="fps", tile_size=8.0, workers=1)
ANGLE = 0.006  # degrees per unit of scan_angle


@pytest.fixture(scope="module")
def street(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return simulated_street(tmp_path_factory, "copc-street", 150_000, 4)


@pytest.fixture(scope="module")
def runs(street: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """The same run written as COPC and as LAZ."""
    folder = tmp_path_factory.mktemp("copc-runs")
    copc, laz = folder / "out.copc.laz", folder / "out.laz"
    pipeline.run(street, copc, **RUN)
    pipeline.run(street, laz, **RUN)
    return copc, laz


def copclib_nodes(path: Path) -> dict[tuple[int, int, int, int], np.ndarray]:
    """Every node's decompressed records, read by copclib (C++ copc-lib and laz-perf, not lazrs)."""
    reader = copclib.FileReader(str(path))
    dtype = laspy.open(path).header.point_format.dtype()
    nodes = {(n.key.d, n.key.x, n.key.y, n.key.z): np.frombuffer(bytes(reader.GetPointData(n)), dtype=dtype)
             for n in reader.GetAllNodes() if n.point_count > 0}
    reader.Close()
    return nodes


def table(records: np.ndarray, point_format: laspy.PointFormat) -> np.ndarray:
    """(n, dims) float64 rows of every dimension of `point_format`, scan angle in degrees, in a canonical order."""
    record = laspy.PackedPointRecord(records, point_format)
    columns = []
    for name in point_format.dimension_names:
        values = np.asarray(record[name], dtype=np.float64)
        columns.append(values * ANGLE if name == "scan_angle" else values)
    rows = np.column_stack(columns)
    return rows[np.lexsort(rows.T[::-1])]


def as_copc(records: np.ndarray, point_format: laspy.PointFormat) -> np.ndarray:
    """Records of a LAS 1.2 format in the COPC format's fields, by field meaning: the test's own conversion."""
    source = laspy.PackedPointRecord(records, point_format)
    target = copc_output.copc_point_format(point_format)
    converted = laspy.PackedPointRecord.zeros(len(records), target)
    for name in target.dimension_names:
        if name == "scan_angle":
            converted[name] = np.round(np.asarray(source["scan_angle_rank"]) / ANGLE).astype(np.int16)
        elif name in point_format.dimension_names:
            converted[name] = np.asarray(source[name])
    return converted.array


def test_copc_run_holds_the_laz_runs_records(runs):
    """laspy (as plain LAZ and through the octree) and copclib all read the LAZ run's records, in format 7."""
    copc, laz = runs
    source = laspy.read(laz)
    assert source.header.point_format.id == 3
    target = copc_output.copc_point_format(source.point_format)
    expected = table(as_copc(source.points.array, source.point_format), target)
    plain = laspy.read(copc)
    assert plain.header.point_format.id == 7 and plain.header.version == "1.4"
    with laspy.CopcReader.open(copc) as reader:
        octree = reader.query().array
    by_copclib = np.concatenate(list(copclib_nodes(copc).values()))
    for records in (plain.points.array, octree, by_copclib):
        assert len(records) == len(source.points) == 75_000
        np.testing.assert_array_equal(table(records, plain.point_format), expected)


def test_copc_header_keeps_crs_provenance_and_bounds(runs, street):
    copc, laz = runs
    header, plain = laspy.open(copc).header, laspy.open(laz).header
    assert header.vlrs[0].user_id == "copc" and header.global_encoding.wkt
    assert any(isinstance(v, laspy.vlrs.known.WktCoordinateSystemVlr) for v in header.vlrs)
    assert header.parse_crs() == laspy.open(street).header.parse_crs() is not None
    record = read_provenance(header)
    assert record is not None and (record["method"], record["ratio"]) == ("fps", 0.5)
    assert header.generating_software == plain.generating_software
    np.testing.assert_allclose(header.mins, plain.mins), np.testing.assert_allclose(header.maxs, plain.maxs)
    assert header.point_count == plain.point_count
    assert list(header.number_of_points_by_return) == list(plain.number_of_points_by_return[:5]) + [0] * 10


def test_bounds_query_returns_exactly_the_points_inside(runs):
    """Boxes with faces on the coordinate grid, so 'inside' is exact in the integer coordinates."""
    copc, _ = runs
    everything = laspy.read(copc)
    header = everything.header
    ints = np.column_stack([everything.X, everything.Y, everything.Z])
    rng = np.random.default_rng(0)
    with laspy.CopcReader.open(copc) as reader:
        for _ in range(5):
            centre = ints[rng.integers(len(ints))]
            low, high = (centre + sign * np.round(rng.uniform(0.5, 4, size=3) / header.scales) for sign in (-1, 1))
            box = Bounds(low * header.scales + header.offsets, high * header.scales + header.offsets)
            inside = np.all((ints >= low) & (ints <= high), axis=1)
            found = reader.query(bounds=box).array
            assert len(found) == inside.sum() > 0
            np.testing.assert_array_equal(table(found, everything.point_format),
                                          table(everything.points.array[inside], everything.point_format))


def priority_parts(las: laspy.LasData, tile: float, seed: int) -> list[TilePart]:
    """The scan cut into square tiles, each in a random 'priority' order; point_source_id = the point's index."""
    records = las.points.array.copy()
    records["point_source_id"] = np.arange(len(records))
    cells = np.floor((np.column_stack([las.x, las.y]) - las.header.mins[:2]) / tile).astype(np.int64)
    code = cells[:, 0] * 100_000 + cells[:, 1]
    rng = np.random.default_rng(seed)
    return [TilePart(t, (0.0, 0.0, 0.0, 0.0), records[rng.permutation(np.flatnonzero(code == c))])
            for t, c in enumerate(np.unique(code))]


def expected_levels(parts: list[TilePart], total: int, node_points: int) -> dict[int, int]:
    """Point id -> level by the documented rule: depth D the least with total * 3 / (4^(D+1) - 1) <= node_points,
    level l for priority (i + 0.5) / n in [C(l-1), C(l)), C(l) = (4^(l+1) - 1) / (4^(D+1) - 1)."""
    depth = 0
    while total * 3 > node_points * (4 ** (depth + 1) - 1):
        depth += 1
    bounds = [(4 ** (level + 1) - 1) / (4 ** (depth + 1) - 1) for level in range(depth + 1)]
    levels = {}
    for part in parts:
        n = len(part.records)
        for i, point in enumerate(part.records["point_source_id"]):
            levels[int(point)] = next(level for level, c in enumerate(bounds) if (i + 0.5) / n < c)
    return levels


@pytest.fixture()
def octree(street_scan: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    """The 60k street written through write_output with 2,000-point nodes (four levels), its parts and path."""
    monkeypatch.setattr(copc_output, "NODE_POINTS", 2_000)
    las = laspy.read(street_scan)
    parts = priority_parts(las, tile=4.0, seed=1)
    path = tmp_path / "tiles.copc.laz"
    meta = OutputMeta(crs_wkt(las.header), [str(street_scan)], 1.0, "random", "test", {})
    assert write_output(path, las.header, len(las.points), iter(parts), meta) == len(las.points)
    return path, parts, las


def test_levels_are_every_tiles_priority_prefix(octree):
    path, parts, las = octree
    levels = expected_levels(parts, len(las.points), 2_000)
    assert max(levels.values()) == 3
    nodes = copclib_nodes(path)
    rank = {int(p): (t, i) for t, part in enumerate(parts) for i, p in enumerate(part.records["point_source_id"])}
    for (level, *_), records in nodes.items():
        ids = records["point_source_id"]
        assert all(levels[int(p)] == level for p in ids)
        order = [rank[int(p)] for p in ids]
        assert order == sorted(order)  # tile by tile, priority order within a tile
    with laspy.CopcReader.open(path) as reader:
        for level in range(4):
            found = np.sort(reader.query(level=level)["point_source_id"])
            np.testing.assert_array_equal(found, sorted(p for p, lv in levels.items() if lv == level))
        coarse = reader.query(resolution=reader.copc_info.spacing)  # the root's spacing: the root only
        assert len(coarse) == sum(1 for lv in levels.values() if lv == 0)


def test_every_node_lies_in_its_cube(octree):
    path, _, las = octree
    with laspy.CopcReader.open(path) as reader:
        low = reader.copc_info.center - reader.copc_info.halfsize
        edge = (reader.copc_info.center[0] + reader.copc_info.halfsize) - low[0]
    header = laspy.open(path).header
    for (level, *key), records in copclib_nodes(path).items():
        xyz = np.column_stack([records[a] for a in "XYZ"]) * header.scales + header.offsets
        side = edge / 2 ** level
        assert np.all(xyz >= low + np.array(key) * side) and np.all(xyz <= low + (np.array(key) + 1) * side)
    assert copclib.FileReader(str(path)).ValidateSpatialBounds(False)


def test_splitting_a_level_in_passes_gives_the_same_nodes(octree, tmp_path, monkeypatch):
    """Levels larger than the load buffer are split into child files first: the nodes do not change."""
    path, parts, las = octree
    monkeypatch.setattr(copc_output, "LOAD_POINTS", 1_500)
    split = tmp_path / "split.copc.laz"
    write_output(split, las.header, len(las.points), iter(parts), OutputMeta(None, [], 1.0, "random", "test", {}))
    whole, pieces = copclib_nodes(path), copclib_nodes(split)
    assert whole.keys() == pieces.keys()
    assert all(np.array_equal(whole[key], pieces[key]) for key in whole)


@pytest.mark.parametrize("point_format", [1, 3])
def test_legacy_point_formats_become_6_and_7_with_every_field(tmp_path, point_format):
    source = random_scan(point_format)
    source_path = tmp_path / "in.las"
    source.write(source_path)
    out = tmp_path / "out.copc.laz"
    pipeline.run(source_path, out, ratio=0.3, method="fps", workers=1, tile_size=10)
    with laspy.CopcReader.open(out) as reader:
        result = reader.query()
        assert reader.header.point_format.id == {1: 6, 3: 7}[point_format]
    assert "confidence" in result.point_format.dimension_names and len(result) == 900
    kept = {tuple(row) for row in table(result.array, result.point_format)}
    converted = as_copc(source.points.array, source.point_format)
    assert kept <= {tuple(row) for row in table(converted, result.point_format)}
    assert len(np.unique(result["scan_angle"])) > 100 and len(np.unique(result["classification"])) > 10


def tail_bytes(records: np.ndarray, count: int) -> np.ndarray:
    """(n, count) last `count` bytes of every record."""
    return np.ascontiguousarray(records).view(np.uint8).reshape(len(records), -1)[:, -count:]


@pytest.mark.parametrize("size", [2, 3, 4, 8, 30])
def test_undocumented_extra_bytes_are_kept_and_read_back(tmp_path, size):
    """Records longer than their format with no extra-bytes VLR: laspy reads the bytes as one `ExtraBytes` field;
    the COPC file must be readable by laspy and `info`, hold each kept point's bytes, and describe them by the
    types LAS 1.4 R15 keeps (not the deprecated arrays, 11-30, which copc.js rejects)."""
    header = laspy.LasHeader(point_format=1, version="1.2")
    header.scales, header.offsets = [0.01] * 3, [0.0] * 3
    header.add_extra_dim(laspy.ExtraBytesParams("raw", f"{size}u1"))
    las = laspy.LasData(header)
    rng = np.random.default_rng(size)
    n = 3_000
    las.x, las.y, las.z = rng.uniform(0, 40, n), rng.uniform(0, 40, n), rng.uniform(0, 3, n)
    las.gps_time = np.arange(n, dtype=np.float64)  # the point's id
    las.raw = rng.integers(0, 256, size=(n, size), dtype=np.uint8)
    documented = tmp_path / "documented.las"
    las.write(documented)
    raw = documented.read_bytes()  # drop the extra-bytes VLR (the only VLR): the bytes become undocumented
    header_size, = struct.unpack_from("<H", raw, 94)
    points_at, = struct.unpack_from("<I", raw, 96)
    stripped = bytearray(raw[:header_size] + raw[points_at:])
    struct.pack_into("<II", stripped, 96, header_size, 0)
    source_path = tmp_path / "in.las"
    source_path.write_bytes(bytes(stripped))
    source = laspy.read(source_path)
    assert list(source.point_format.extra_dimension_names) == ["ExtraBytes"] and not source.header.vlrs
    out = tmp_path / "out.copc.laz"
    pipeline.run(source_path, out, ratio=0.3, method="fps", workers=1, tile_size=10)
    result = laspy.read(out)
    assert result.header.point_format.id == 6 and len(result.points) == 900
    ids = result.gps_time.astype(np.int64)
    np.testing.assert_array_equal(tail_bytes(result.points.array, size), tail_bytes(source.points.array, size)[ids])
    np.testing.assert_array_equal(result.X, source.X[ids])
    with laspy.CopcReader.open(out) as reader:
        assert len(reader.query()) == 900
    info = CliRunner().invoke(cli, ["info", str(out)], prog_name="pipeline")
    assert info.exit_code == 0 and "900" in info.output, info.output
    types = [f.data_type for v in result.header.vlrs if isinstance(v, ExtraBytesVlr) for f in v.extra_bytes_structs]
    assert len(types) == size and set(types) == {1}  # one u1 field per byte

def test_input_evlrs_follow_the_hierarchy(tmp_path):
    source = random_scan(6)
    source.header.evlrs = laspy.vlrs.vlrlist.VLRList([laspy.VLR("survey", 7, "note", b"x" * 70_000)])
    out = tmp_path / "out.copc.laz"
    write_output(out, source.header, 3_000, iter([TilePart(0, (0.0, 0.0, 0.0, 0.0), source.points.array)]),
                 OutputMeta(None, [], 1.0, "random", "test", {}))
    evlrs = laspy.read(out).header.evlrs
    assert [(v.user_id, v.record_id) for v in evlrs] == [("copc", 1000), ("survey", 7)]
    assert bytes(evlrs[1].record_data) == b"x" * 70_000
    with laspy.CopcReader.open(out) as reader:
        assert len(reader.query()) == 3_000


def test_waveform_formats_are_refused(tmp_path):
    source = random_scan(4)
    with pytest.raises(PipelineError, match="waveform"):
        write_output(tmp_path / "out.copc.laz", source.header, 3_000,
                     iter([TilePart(0, (0.0, 0.0, 0.0, 0.0), source.points.array)]),
                     OutputMeta(None, [], 1.0, "random", "test", {}))
    assert list(tmp_path.iterdir()) == []


def test_failed_write_leaves_no_output_and_no_scratch(street_scan, tmp_path):
    las = laspy.read(street_scan)
    meta = OutputMeta(None, [], 1.0, "random", "test", {})
    folder = tmp_path / "out"
    folder.mkdir()

    def failing_parts():
        yield TilePart(0, (0.0, 0.0, 0.0, 0.0), las.points.array[:1000])
        raise RuntimeError("tile 1 could not be read")

    with pytest.raises(RuntimeError, match="tile 1"):
        write_output(folder / "out.copc.laz", las.header, 2000, failing_parts(), meta)
    assert list(folder.iterdir()) == []
    with pytest.raises(PipelineError, match="wrote 1000 points where 2000 were planned"):
        write_output(folder / "out.copc.laz", las.header, 2000,
                     iter([TilePart(0, (0.0, 0.0, 0.0, 0.0), las.points.array[:1000])]), meta)
    assert list(folder.iterdir()) == []


def test_overwrite_replaces_only_a_las_file(street_scan, tmp_path):
    out = tmp_path / "out.copc.laz"
    out.write_text("notes")
    with pytest.raises(PipelineError, match="already exists"):
        pipeline.run(street_scan, out, **RUN)
    with pytest.raises(PipelineError, match="not a LAZ file"):
        pipeline.run(street_scan, out, overwrite=True, **RUN)
    assert out.read_text() == "notes"


def test_a_generated_copc_file_reads_by_its_chunk_table(runs, tmp_path):
    """Our COPC output as an input: a variable-chunk LAZ file, read by its chunk table (lazrs's own seek
    assumes equal chunks). Windows that start inside a node, cross node borders and end at the last point
    give laspy's records for them; a run on it keeps the exact count."""
    copc, _ = runs
    source = LasSource(copc)
    assert variable_chunks(source.header)
    every = laspy.read(copc).points.array
    total = len(every)
    for start, count in ((0, 1), (1, 999), (4_321, 20_000), (total - 7, 7), (0, total)):
        np.testing.assert_array_equal(source.read(start, count), every[start:start + count])
    report = pipeline.run(copc, tmp_path / "again.laz", ratio=0.5, method="random", workers=1, chunk_points=10_000)
    assert report.output_points == round(0.5 * total) and laspy.read(tmp_path / "again.laz").header.point_count == report.output_points


def test_copc_input_to_copc_output(tmp_path):
    source = shared_file("lone-star.copc.laz")
    out = tmp_path / "lone-star.copc.laz"
    report = pipeline.run(source, out, ratio=0.05, method="random", workers=1)
    with laspy.CopcReader.open(out) as reader:
        assert len(reader.query()) == report.output_points
        assert [v.user_id for v in reader.header.vlrs].count("copc") == 1
    assert sum(len(r) for r in copclib_nodes(out).values()) == report.output_points


def two_extra_bytes_vlrs(point_format: int, n: int = 3_000) -> laspy.LasData:
    """A scan whose extra bytes two VLRs describe, as a RIEGL scan's (las_with_several_extra_byte_bloc.laz): the
    first `Deviation` (u2, no-data 0) and `range` (i4, scaled, offset, no-data -1), the second `confidence` (u1),
    which laspy reads as one unnamed `ExtraBytes` byte; gps_time is the point's index."""
    header = laspy.LasHeader(point_format=point_format, version="1.4" if point_format >= 6 else "1.2")
    header.scales, header.offsets = [0.01] * 3, [0.0] * 3
    header.add_extra_dims([
        laspy.ExtraBytesParams("Deviation", "u2", "Pulse shape deviation", no_data=[0]),
        laspy.ExtraBytesParams("range", "i4", "range to target", offsets=[10.0], scales=[0.001], no_data=[-1]),
        laspy.ExtraBytesParams("confidence", "u1", "confidence values")])
    first = header.vlrs.get("ExtraBytesVlr")[0]
    second = ExtraBytesVlr()
    second.extra_bytes_structs.append(first.extra_bytes_structs.pop())
    header.vlrs.append(second)  # in place: assigning a list makes laspy merge them again
    las = laspy.LasData(header)
    rng = np.random.default_rng(point_format)
    las.x, las.y, las.z = rng.uniform(0, 40, n), rng.uniform(0, 40, n), rng.uniform(0, 3, n)
    las.gps_time = np.arange(n, dtype=np.float64)
    las.Deviation = rng.integers(0, 2 ** 16, n)
    las.points.array["range"] = rng.integers(-(2 ** 31), 2 ** 31, n)  # the stored integers, not scaled values
    las.confidence = rng.integers(0, 256, n)  # in memory the field has its name; read back, laspy calls it ExtraBytes
    return las


@pytest.mark.parametrize("point_format", [1, 6])
def test_every_extra_bytes_field_keeps_its_description_without_min_max(tmp_path, point_format):
    """One extra-bytes VLR describing each field of the input's VLRs (name, type, no-data, scale, offset,
    description) with no min/max: laspy's placeholders (min 2^64-1, max 0), which the writer never filled, made
    copc.js fail to open the file ("Cannot convert bigint to number")."""
    source = two_extra_bytes_vlrs(point_format)
    source_path = tmp_path / "in.las"
    source.write(source_path)
    source = laspy.read(source_path)
    assert list(source.point_format.extra_dimension_names) == ["Deviation", "range", "ExtraBytes"]
    out = tmp_path / "out.copc.laz"
    pipeline.run(source_path, out, ratio=0.3, method="fps", workers=1, tile_size=10)
    header = laspy.open(out).header
    [vlr] = [v for v in header.vlrs if isinstance(v, ExtraBytesVlr)]
    fields = vlr.extra_bytes_structs
    described = [field for v in source.header.vlrs if isinstance(v, ExtraBytesVlr) for field in v.extra_bytes_structs]
    assert [(f.name, f.data_type, f.description) for f in fields] == [(b"Deviation", 3, b"Pulse shape deviation"),
                                                                       (b"range", 6, b"range to target"),
                                                                       (b"confidence", 1, b"confidence values")]
    for field, before in zip(fields, described):
        assert field.options == before.options & ~(field.MIN_BIT_MASK | field.MAX_BIT_MASK)
        assert field.min is None and field.max is None and not any(bytes(field._min) + bytes(field._max))
        for name in ("no_data", "scale", "offset"):
            np.testing.assert_array_equal(getattr(field, name), getattr(before, name))
    result = laspy.read(out)
    assert list(result.point_format.extra_dimension_names) == ["Deviation", "range", "confidence"]
    ids = result.gps_time.astype(np.int64)
    assert len(ids) == 900
    np.testing.assert_array_equal(result.confidence, source.ExtraBytes[ids])
    np.testing.assert_array_equal(result.Deviation, source.Deviation[ids])
    np.testing.assert_allclose(result.range, source.range[ids])


def test_cube_on_holds_its_box_as_readers_compute_it():
    """Readers take the cube as centre -+ halfsize in float64 (copc.js) or as centre - halfsize plus the edge taken
    from x (laspy): both must hold the box exactly, the cube's minimum and edge within rounding of the box's minimum
    and longest side (copclib starts its cells at the header's minimum, with that edge)."""
    rng = np.random.default_rng(0)
    for _ in range(2_000):
        first = rng.integers(0, 10 ** 9, 3)  # the box's corners in LAS integers
        last = first + rng.integers(0, 10 ** 6, 3)
        scale, offset = float(rng.choice([0.01, 0.001, 0.00025])), rng.uniform(-1e6, 1e6, 3).round()
        mins, maxs = first * scale + offset, last * scale + offset
        cube = copc_output.Cube.on(mins, maxs, scale)
        low, high = cube.center - cube.halfsize, cube.center + cube.halfsize
        assert np.all(low <= mins) and np.all(high >= maxs) and np.all(low + (high[0] - low[0]) >= maxs)
        rounding = np.spacing(np.abs(np.concatenate([mins, maxs])).max())  # a coordinate's rounding step
        assert np.all(np.abs(low - mins) <= 4 * rounding)
        assert abs(cube.halfsize - max((maxs - mins).max(), scale) / 2) <= 4 * rounding


def test_every_point_lies_in_the_cube_readers_compute(tmp_path):
    """autzen_trim's box, where centre = minimum + halfsize rounds so that centre - halfsize was 636006.3900000001
    for a minimum x of 636006.39: its boundary points fell outside the cube (copc-validator's xyz check)."""
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales, header.offsets = [0.01] * 3, [0.0] * 3
    low, high = np.array([63600639, 84893624, 40666]), np.array([63717798, 84949478, 51831])
    rng = np.random.default_rng(5)
    ints = np.vstack([low, high, rng.integers(low, high, size=(3_000, 3), endpoint=True)])
    records = laspy.ScaleAwarePointRecord.zeros(len(ints), header=header)
    records.X, records.Y, records.Z = ints.T
    out = tmp_path / "box.copc.laz"
    write_output(out, header, len(ints), iter([TilePart(0, (0.0, 0.0, 0.0, 0.0), records.array)]),
                 OutputMeta(None, [], 1.0, "random", "test", {}))
    points = laspy.read(out)
    xyz = np.column_stack([points.x, points.y, points.z])
    with laspy.CopcReader.open(out) as reader:
        center, halfsize = np.asarray(reader.copc_info.center, dtype=np.float64), float(reader.copc_info.halfsize)
    assert np.all(xyz >= center - halfsize) and np.all(xyz <= center + halfsize)
    assert copclib.FileReader(str(out)).ValidateSpatialBounds(False)


def crs_records(header: laspy.LasHeader) -> list[tuple[str, int]]:
    """(user id, record id) of every CRS record: LASF_Projection's GeoTIFF keys and WKT, and libLAS's WKT copy."""
    return [(v.user_id, v.record_id) for v in [*header.vlrs, *(header.evlrs or [])]
            if v.user_id == "LASF_Projection" or (v.user_id, v.record_id) == ("liblas", 2112)]


def test_geotiff_only_input_gets_a_wkt1_crs_record(runs, street):
    """The street's CRS is GeoTIFF keys only: the COPC file's one WKT record is WKT1, as LAS 1.4 means it (pyproj's
    default WKT2 is not: proj4js, copc.js's projection library, cannot read it)."""
    copc, _ = runs
    header = laspy.open(copc).header
    [wkt] = [v for v in header.vlrs if isinstance(v, laspy.vlrs.known.WktCoordinateSystemVlr)]
    assert wkt.string.startswith(("PROJCS[", "GEOGCS[", "COMPD_CS[")), wkt.string[:40]
    assert header.parse_crs().equals(laspy.open(street).header.parse_crs(), ignore_axis_order=True)


def test_las_wkt_is_wkt1_where_pyproj_can_write_it():
    assert las_wkt(pyproj.CRS("EPSG:26917").to_wkt()).startswith('PROJCS["NAD83 / UTM zone 17N"')
    three_d = pyproj.CRS("EPSG:4979").to_wkt()  # a 3-D geographic CRS: no WKT1
    assert las_wkt(three_d) == three_d
    assert las_wkt("not a WKT") == "not a WKT"


def test_copc_holds_one_crs_record(runs, tmp_path):
    """GeoTIFF keys, a WKT record and libLAS's copy of it (as autzen_trim holds) become one WKT record: under the WKT
    bit readers must ignore GeoTIFF keys, and a second WKT record leaves them to choose."""
    copc, _ = runs
    assert crs_records(laspy.open(copc).header) == [("LASF_Projection", 2112)]  # GeoTIFF keys only, before
    source = random_scan(3)
    [geokeys] = [v for v in street_header().vlrs if isinstance(v, GeoKeyDirectoryVlr)]
    wkt = pyproj.CRS("EPSG:26917").to_wkt("WKT1_GDAL")
    source.header.vlrs.extend([geokeys, laspy.vlrs.known.WktCoordinateSystemVlr(wkt),
                               laspy.VLR("liblas", 2112, "OGR variant of OpenGIS WKT SRS", wkt.encode() + b"\0")])
    source_path = tmp_path / "in.las"
    source.write(source_path)
    assert crs_records(laspy.open(source_path).header) == [("LASF_Projection", 34735), ("LASF_Projection", 2112),
                                                           ("liblas", 2112)]
    out = tmp_path / "out.copc.laz"
    pipeline.run(source_path, out, ratio=0.3, method="fps", workers=1, tile_size=10)
    header = laspy.open(out).header
    assert crs_records(header) == [("LASF_Projection", 2112)]
    assert header.parse_crs().equals(pyproj.CRS("EPSG:26917"), ignore_axis_order=True)


@pytest.mark.skipif(shutil.which("pdal") is None,
                    reason="PDAL's `pdal` command is not installed (Debian bookworm has no pdal package)")
def test_pdal_reads_every_point(runs, tmp_path):
    copc, laz = runs
    info = json.loads(subprocess.run(["pdal", "info", "--summary", str(copc)], check=True, capture_output=True,
                                     text=True).stdout)
    assert info["summary"]["num_points"] == 75_000
    copy = tmp_path / "copy.las"
    subprocess.run(["pdal", "translate", "--reader", "readers.copc", str(copc), str(copy)], check=True)
    result = laspy.read(copy)
    np.testing.assert_array_equal(table(result.points.array, result.point_format),
                                  table(laspy.read(copc).points.array, result.point_format))
