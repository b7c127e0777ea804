"""Every LAS point format and version in, the same format, header and records out (generated files)."""
from __future__ import annotations

import laspy
import numpy as np
import pytest

import pipeline
from tests.conftest import shared_file

VERSION_OF_FORMAT = {0: "1.2", 1: "1.1", 2: "1.2", 3: "1.2", 4: "1.3", 5: "1.3",
                     6: "1.4", 7: "1.4", 8: "1.4", 9: "1.4", 10: "1.4"}


def random_scan(point_format: int, n: int = 3_000, seed: int = 0) -> laspy.LasData:
    """Random values in every dimension of the format (within each field's range), plus one extra-bytes dimension."""
    header = laspy.LasHeader(version=VERSION_OF_FORMAT[point_format], point_format=point_format)
    header.scales, header.offsets = [0.001] * 3, [1000.0, 2000.0, 0.0]
    header.add_extra_dim(laspy.ExtraBytesParams(name="confidence", type=np.float32))
    las = laspy.LasData(header)
    rng = np.random.default_rng(seed + point_format)
    las.x, las.y, las.z = 1000 + rng.uniform(0, 40, n), 2000 + rng.uniform(0, 40, n), rng.uniform(0, 3, n)
    raw = las.points.array
    for name in raw.dtype.names:
        if name in ("X", "Y", "Z"):
            continue
        field = raw[name]
        if field.dtype.kind in "ui":
            info = np.iinfo(field.dtype)
            raw[name] = rng.integers(info.min, info.max, size=n, endpoint=True, dtype=field.dtype)
        elif field.dtype.kind == "f":
            raw[name] = rng.normal(size=n).astype(field.dtype)
    return las


@pytest.mark.parametrize("point_format", sorted(VERSION_OF_FORMAT))
def test_every_point_format_round_trips(tmp_path, point_format):
    """Uncompressed, so random bit patterns test the pipeline, not lazrs (whose point format 9/10 codec
    does not round-trip random waveform fields even in a plain laspy write and read)."""
    source = random_scan(point_format)
    source_path = tmp_path / "in.las"
    source.write(source_path)
    out = tmp_path / "out.las"
    pipeline.run(source_path, out, ratio=0.3, method="fps", workers=1, tile_size=10)  # picks, not moves
    result = laspy.read(out)
    assert result.header.version == VERSION_OF_FORMAT[point_format]
    assert result.header.point_format.id == point_format
    assert len(result.points) == 900
    rows = lambda a: np.ascontiguousarray(a).view(np.dtype((np.void, a.dtype.itemsize)))  # noqa: E731
    assert np.isin(rows(result.points.array), rows(laspy.read(source_path).points.array)).all()


def test_evlrs_survive(tmp_path):
    source = random_scan(6)
    source.header.evlrs = laspy.vlrs.vlrlist.VLRList(
        [laspy.VLR(user_id="survey", record_id=7, description="note", record_data=b"x" * 70_000)])
    source_path = tmp_path / "evlr.las"
    source.write(source_path)
    pipeline.run(source_path, tmp_path / "out.las", ratio=0.5, workers=1)
    evlrs = laspy.read(tmp_path / "out.las").header.evlrs
    assert [(v.user_id, v.record_id, bytes(v.record_data)) for v in evlrs] == [("survey", 7, b"x" * 70_000)]


def test_las_1_0_is_read_as_1_1(tmp_path):
    """laspy reads 1.1-1.4 only; a 1.0 file (same layout as 1.1) is read and written back as 1.1."""
    source = random_scan(1)
    path = tmp_path / "v10.las"
    source.write(path)
    data = bytearray(path.read_bytes())
    data[25] = 0  # LAS 1.0
    path.write_bytes(bytes(data))
    out = tmp_path / "out.las"
    pipeline.run(path, out, ratio=0.5, workers=1)
    result = laspy.read(out)
    assert result.header.version == "1.1" and len(result.points) == 1_500


@pytest.mark.parametrize("name", ["edge-cases/fullwave.laz", "edge-cases/simple1_3.las"])
def test_real_waveform_files_keep_every_field(tmp_path, name):
    source_path = shared_file(name)
    out = tmp_path / f"out{source_path.suffix}"
    pipeline.run(source_path, out, ratio=0.5, method="fps", workers=1)  # picks, not moves
    source, result = laspy.read(source_path), laspy.read(out)
    assert result.header.point_format.id == source.header.point_format.id
    rows = lambda a: np.ascontiguousarray(a).view(np.dtype((np.void, a.dtype.itemsize)))  # noqa: E731
    assert np.isin(rows(result.points.array), rows(source.points.array)).all()
    assert sorted((v.user_id, v.record_id) for v in result.header.vlrs if v.user_id != "laszip encoded") == \
        sorted([(v.user_id, v.record_id) for v in source.header.vlrs if v.user_id != "laszip encoded"]
               + [("lidar-simplify", 1)])  # every input VLR, plus the run record (pipeline.io.provenance)


@pytest.mark.parametrize("layout", ["<f4", "<f8", ">f8", "ascii"])
def test_ply_coordinates_land_on_the_grid_as_laspys_scaled_assignment_puts_them(tmp_path, layout):
    """PlySource puts x, y, z on its millimetre grid without laspy's scaled assignment (its copies cost a
    fifth of reading a PLY): the integers must be the ones that assignment gives, half steps included."""
    from plyfile import PlyData, PlyElement

    from pipeline.io.ply_source import XYZ, PlySource

    rng = np.random.default_rng(3)
    xyz = rng.uniform(0, 50, (2_000, 3)) + [500_000.0, 4_000_000.0, 100.0]
    xyz[:200] = np.floor(xyz[:200] * 1000) / 1000 + 0.0005  # half a step past a grid line
    dtype = "f4" if layout == "<f4" else "f8"
    vertices = np.zeros(len(xyz), dtype=[(axis, layout if layout != "ascii" else dtype) for axis in XYZ])
    for axis, name in enumerate(XYZ):
        vertices[name] = xyz[:, axis]
    path = tmp_path / "cloud.ply"
    PlyData([PlyElement.describe(vertices, "vertex")], text=layout == "ascii",
            byte_order=">" if layout == ">f8" else "<").write(str(path))
    source = PlySource(path)
    expected = laspy.ScaleAwarePointRecord.zeros(len(xyz), header=source.header)
    for name in XYZ:
        setattr(expected, name, np.asarray(PlyData.read(str(path))["vertex"][name], dtype=np.float64))
    got = source.read(0, len(xyz))
    for name in "XYZ":
        np.testing.assert_array_equal(got[name], expected.array[name])


@pytest.mark.parametrize("batch_rows", [700, 2_500, 200_000])
def test_a_laz_output_holds_every_tiles_records_in_order_whatever_the_compression_batch(tmp_path, monkeypatch,
                                                                                        batch_rows):
    """Tiles' parts are joined into batches so lazrs compresses whole chunks side by side (pipeline.io.writers):
    batches that split the parts unevenly, or one that holds them all, still write every record once, in order."""
    from pipeline.io import writers
    from pipeline.io.output_meta import OutputMeta
    from tiling.assemble import TilePart

    las = random_scan(6, n=5_000)
    sizes = [0, 1, 450, 999, 3, 1_547, 2_000]  # 5,000 in all, an empty tile among them
    cuts = np.cumsum([0, *sizes])
    parts = [TilePart(tile, (0.0, 0.0, 1.0, 1.0), las.points.array[cuts[tile]:cuts[tile + 1]])
             for tile in range(len(sizes))]
    monkeypatch.setattr(writers, "COMPRESS_ROWS", batch_rows)
    out = tmp_path / "batched.laz"
    written = writers.write_output(out, las.header, 5_000, iter(parts), OutputMeta(None, [], 1.0, "random", "test"))
    assert written == 5_000
    assert np.array_equal(laspy.read(out).points.array, las.points.array)
    assert [len(batch) for batch in writers.batched((p.records for p in parts), 2_500)] == [3_000, 2_000]  # a tail


def ply_with(path, properties: dict[str, np.ndarray], n: int = 4_000, seed: int = 5):
    """A binary PLY of n random vertices with x, y, z and the given properties; returns its vertex array."""
    from plyfile import PlyData, PlyElement

    rng = np.random.default_rng(seed)
    vertex = np.zeros(n, dtype=[("x", "f8"), ("y", "f8"), ("z", "f8")]
                      + [(name, values.dtype.str) for name, values in properties.items()])
    vertex["x"], vertex["y"], vertex["z"] = rng.uniform(0, 30, n), rng.uniform(0, 30, n), rng.uniform(0, 3, n)
    for name, values in properties.items():
        vertex[name] = values
    PlyData([PlyElement.describe(vertex, "vertex")]).write(str(path))
    return vertex


def kept_vertices(las: laspy.LasData, vertex: np.ndarray) -> np.ndarray:
    """The PLY vertices the output kept, in its order, matched on the millimetre grid."""
    key = lambda x, y, z: (round(x * 1000), round(y * 1000), round(z * 1000))  # noqa: E731
    rows = {key(*v): i for i, v in enumerate(zip(vertex["x"], vertex["y"], vertex["z"]))}
    return vertex[[rows[key(*p)] for p in zip(las.x, las.y, las.z)]]


def test_ply_properties_named_as_las_dimensions_fill_them_and_the_rest_survive_renamed(tmp_path):
    """PDAL and CloudCompare export `intensity`, `classification`, `GpsTime` and the like: they fill those LAS
    dimensions (they crashed the run as duplicate extra bytes), a property named as a LAS field it cannot fill
    (`X`, `scan_angle`) or longer than LAS's 32 bytes is kept as an extra dimension under another name, with its
    PLY name in the description, and a PLY without returns is written as single returns (LAS 1.4 needs 1+)."""
    n, rng = 4_000, np.random.default_rng(1)
    long_name = "a_property_name_longer_than_the_32_bytes_las_allows"
    vertex = ply_with(tmp_path / "in.ply", {
        "intensity": rng.integers(0, 65536, n).astype("u2"), "classification": rng.integers(0, 20, n).astype("u1"),
        "GpsTime": rng.uniform(0, 1e5, n), long_name: rng.normal(size=n).astype("f4"),
        "X": rng.normal(size=n).astype("f4"), "scan_angle": rng.uniform(-20, 20, n).astype("f4")}, n)
    pipeline.run(tmp_path / "in.ply", tmp_path / "out.laz", ratio=0.5, method="fps", workers=1)
    las = laspy.read(tmp_path / "out.laz")
    src = kept_vertices(las, vertex)
    np.testing.assert_array_equal(las.intensity, src["intensity"])
    np.testing.assert_array_equal(las.classification, src["classification"])
    np.testing.assert_array_equal(las.gps_time, src["GpsTime"])
    extras = {e.name: e.description for e in las.point_format.extra_dimensions}
    assert extras == {"ply_a_property_name_longer_than_": "PLY a_property_name_longer_than_", "ply_X": "PLY X",
                      "ply_scan_angle": "PLY scan_angle"}
    np.testing.assert_array_equal(las["ply_a_property_name_longer_than_"], src[long_name])
    np.testing.assert_array_equal(las["ply_X"], src["X"])
    np.testing.assert_array_equal(las["ply_scan_angle"], src["scan_angle"])
    assert (las.return_number == 1).all() and (las.number_of_returns == 1).all()


@pytest.mark.parametrize("dtype, values, expected", [
    ("u1", [0, 128, 255], [0, 128 * 257, 65535]),
    ("u2", [0, 40_000, 65535], [0, 40_000, 65535]),       # 16-bit colours as they are (x257 wrapped them)
    ("f4", [0.0, 0.5, 1.0], [0, 32768, 65535]),           # 0-1 floats (became 0)
    ("f4", [0.0, 128.0, 255.0], [0, 128 * 257, 65535]),   # 0-255 floats
])
def test_ply_colours_of_any_type_fill_las_s_16_bit_range(tmp_path, dtype, values, expected):
    n = 3_000
    channel = np.resize(np.array(values, dtype=dtype), n)
    vertex = ply_with(tmp_path / "in.ply", {"red": channel, "green": channel, "blue": channel}, n)
    pipeline.run(tmp_path / "in.ply", tmp_path / "out.las", ratio=0.5, method="fps", workers=1)
    las = laspy.read(tmp_path / "out.las")
    lookup = dict(zip(np.array(values, dtype=dtype).tolist(), expected))
    wanted = [lookup[v] for v in kept_vertices(las, vertex)["red"].tolist()]
    for name in ("red", "green", "blue"):
        np.testing.assert_array_equal(las[name], wanted)


def test_a_ply_list_property_on_vertices_is_refused_in_one_line(tmp_path):
    from plyfile import PlyData, PlyElement

    from pipeline.io.ply_source import PlySource

    vertex = np.empty(3, dtype=[("x", "f8"), ("y", "f8"), ("z", "f8"), ("ids", "O")])
    vertex["x"] = vertex["y"] = vertex["z"] = [0.0, 1.0, 2.0]
    vertex["ids"] = [np.array([1, 2], dtype="i4")] * 3
    PlyData([PlyElement.describe(vertex, "vertex", len_types={"ids": "u1"}, val_types={"ids": "i4"})]).write(
        str(tmp_path / "in.ply"))
    with pytest.raises(pipeline.PipelineError, match="'ids' is a list"):
        PlySource(tmp_path / "in.ply")


def test_extra_bytes_min_and_max_are_the_data_s_or_marked_absent(tmp_path):
    """A LAS/LAZ output's extra-bytes fields whose min and max are marked present hold the kept points' own:
    laspy's tracking as it writes left a field with a no-data value at its placeholders (min 2^64-1 above max
    0) and others with a min above the data's, so they are marked absent. Readers such as copc.js take marked
    values as they are."""
    from laspy.vlrs.known import ExtraBytesVlr

    header = laspy.LasHeader(version="1.4", point_format=6)
    header.add_extra_dims([laspy.ExtraBytesParams("deviation", "u2", no_data=[0]),
                           laspy.ExtraBytesParams("plain", "i4")])
    las = laspy.LasData(header)
    rng = np.random.default_rng(4)
    las.x, las.y, las.z = rng.uniform(0, 40, (3, 5_000))
    las.deviation, las.plain = rng.integers(1, 900, 5_000), rng.integers(-50, 50, 5_000)
    las.write(tmp_path / "in.las")
    pipeline.run(tmp_path / "in.las", tmp_path / "out.laz", ratio=0.2, method="random", workers=1)
    out = laspy.read(tmp_path / "out.laz")
    fields = {f.name.rstrip(b"\0").decode(): f for v in out.header.vlrs if isinstance(v, ExtraBytesVlr)
              for f in v.extra_bytes_structs}
    for name, field in fields.items():
        values = np.asarray(out[name])
        if field.options & field.MIN_BIT_MASK:
            assert field.min[0] <= values.min() and field.max[0] >= values.max(), name
    assert not fields["deviation"].options & fields["deviation"].MIN_BIT_MASK
    assert fields["deviation"].no_data[0] == 0  # what a reader needs is kept
