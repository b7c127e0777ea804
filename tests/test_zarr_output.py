"""The zarr output as xarray, pyproj and rioxarray users open it: no warnings, x/y/z as coordinates of `point`,
CF attributes, the CRS as `spatial_ref`, the tile index along `tile`, and the same points as the LAS output."""
from __future__ import annotations

import warnings
from pathlib import Path

import laspy
import numpy as np
import pyproj
import pytest
import xarray as xr
import zarr

import pipeline
import pipeline.io.zarr_output
from tests.conftest import shared_file

SMALL_CHUNK = 1_000  # a zarr chunk far smaller than the output, so the streaming writer flushes many times
SETTINGS = dict(ratio=0.2, method="random", workers=1)


def header_of(path: Path) -> laspy.LasHeader:
    """A LAS/LAZ file's header, the file closed again."""
    with laspy.open(path) as reader:
        return reader.header


def open_quietly(path: Path) -> xr.Dataset:
    """xarray's default way in, with any warning raised as an error."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return xr.open_zarr(path)


@pytest.fixture(scope="module")
def street_outputs(street_scan: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """The generated street scan simplified twice with the same settings: to zarr (small chunks) and to LAS."""
    folder = tmp_path_factory.mktemp("zarr_output")
    store, las = folder / "street.zarr", folder / "street.las"
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(pipeline.io.zarr_output, "ZARR_CHUNK", SMALL_CHUNK)
        pipeline.run(street_scan, store, **SETTINGS)
    pipeline.run(street_scan, las, **SETTINGS)
    return store, las


def test_opens_without_warnings_with_xyz_as_coordinates(street_outputs):
    store, las_path = street_outputs
    dataset = open_quietly(store)
    points = header_of(las_path).point_count
    assert dataset.sizes["point"] == points
    for axis in "xyz":
        assert axis in dataset.coords and axis not in dataset.data_vars
        assert dataset[axis].dims == ("point",) and dataset[axis].dtype == np.float64
    assert dataset["intensity"].dims == ("point",)
    assert {"x", "y", "z", "spatial_ref"} <= set(dataset["intensity"].coords)
    assert dataset["x"].encoding["chunks"] == (SMALL_CHUNK,) and points > 3 * SMALL_CHUNK
    assert dataset.attrs["provenance"]["method"] == "random" and dataset.attrs["provenance"]["ratio"] == 0.2


def test_values_equal_the_las_output_point_for_point(street_outputs):
    store, las_path = street_outputs
    dataset, las = open_quietly(store), laspy.read(las_path)
    for name in las.point_format.dimension_names:
        variable = name.lower() if name in ("X", "Y", "Z") else name
        expected = np.asarray(las[variable])
        assert dataset[variable].attrs["las_dimension"] == name
        assert dataset[variable].dtype == expected.dtype, name
        np.testing.assert_array_equal(dataset[variable].values, expected, err_msg=name)
    for axis, name in zip("xyz", "XYZ"):  # the recorded scale and offset give back the LAS integers
        attrs = dataset[axis].attrs
        integers = np.round((dataset[axis].values - attrs["las_add_offset"]) / attrs["las_scale_factor"])
        np.testing.assert_array_equal(integers, np.asarray(las[name]))


def test_a_user_can_select_by_tile_and_filter_by_class(street_outputs):
    store, las_path = street_outputs
    dataset, las = open_quietly(store), laspy.read(las_path)
    tile = dataset.sel(tile=dataset["tile"].values[len(dataset["tile"]) // 2])
    start, count = int(tile["tile_start"]), int(tile["tile_count"])
    part = dataset.isel(point=slice(start, start + count))
    assert part.sizes["point"] == count > 0
    assert float(tile["tile_xmin"]) <= part["x"].min() and part["x"].max() <= float(tile["tile_xmax"])
    assert float(tile["tile_ymin"]) <= part["y"].min() and part["y"].max() <= float(tile["tile_ymax"])
    ground = dataset.where((dataset["classification"] == 2).compute(), drop=True)
    assert ground.sizes["point"] == int((np.asarray(las.classification) == 2).sum()) > 0
    assert (ground["classification"] == 2).all() and ground.sizes["tile"] == dataset.sizes["tile"]


def test_tile_index_arrays_cover_the_points_contiguously(street_outputs):
    store, _ = street_outputs
    dataset = open_quietly(store)
    starts, counts = dataset["tile_start"].values, dataset["tile_count"].values
    assert dataset["tile_count"].dims == ("tile",) and len(np.unique(dataset["tile"].values)) == dataset.sizes["tile"]
    assert counts.sum() == dataset.sizes["point"]
    np.testing.assert_array_equal(starts, np.concatenate([[0], np.cumsum(counts)[:-1]]))
    assert "tile_index" not in zarr.open_group(str(store), mode="r").attrs  # no longer a JSON attribute


def test_spatial_ref_is_the_input_crs_and_every_variable_points_to_it(street_outputs, street_scan):
    store, _ = street_outputs
    dataset = open_quietly(store)
    source = header_of(street_scan).parse_crs()
    spatial_ref = dataset["spatial_ref"]
    assert spatial_ref.ndim == 0 and np.issubdtype(spatial_ref.dtype, np.integer)
    assert pyproj.CRS.from_wkt(spatial_ref.attrs["crs_wkt"]) == source
    assert pyproj.CRS.from_wkt(spatial_ref.attrs["spatial_ref"]) == source
    assert pyproj.CRS.from_cf(spatial_ref.attrs) == source
    assert spatial_ref.attrs["grid_mapping_name"] == "transverse_mercator"  # UTM 17N, from pyproj's to_cf
    assert all(variable.attrs["grid_mapping"] == "spatial_ref" for variable in dataset.data_vars.values())
    assert pyproj.CRS.from_wkt(zarr.open_group(str(store), mode="r").attrs["crs_wkt"]) == source
    for name in ("x", "y", "tile_xmin", "tile_ymax"):
        assert dataset[name].attrs["units"] == "metre"
    for name in ("x", "y"):  # CF's roles, which GDAL and cf_xarray read
        assert dataset[name].attrs["axis"] == name.upper()
        assert dataset[name].attrs["standard_name"] == f"projection_{name}_coordinate"
    assert dataset["z"].attrs["axis"] == "Z" and dataset["z"].attrs["positive"] == "up"


def test_classification_and_flags_carry_cf_meanings(street_outputs):
    dataset = open_quietly(street_outputs[0])
    classes = dataset["classification"].attrs
    meanings = dict(zip(classes["flag_values"], classes["flag_meanings"].split()))
    assert len(meanings) == len(classes["flag_values"]) == len(classes["flag_meanings"].split())
    assert meanings[2] == "ground" and meanings[6] == "building" and meanings[11] == "road_surface"
    assert set(np.unique(dataset["classification"].values)) <= set(meanings)  # the simulator uses ASPRS codes
    assert dataset["synthetic"].attrs["flag_meanings"] == "false true"
    assert dataset["return_number"].attrs["valid_range"] == [1, 7]  # point format 3: three bits
    assert "units" not in dataset["intensity"].attrs  # dimensionless


def test_autzen_units_are_its_crs_feet(tmp_path):
    source = shared_file("autzen_trim.laz")
    store = tmp_path / "autzen.zarr"
    pipeline.run(source, store, ratio=0.1, method="random", workers=1, tile_size=60)
    dataset = open_quietly(store)
    crs = header_of(source).parse_crs()
    unit = next(axis.unit_name for axis in crs.axis_info if axis.direction == "east")
    assert "foot" in unit
    assert dataset["x"].attrs["units"] == dataset["y"].attrs["units"] == dataset["tile_xmin"].attrs["units"] == unit
    assert pyproj.CRS.from_cf(dataset["spatial_ref"].attrs) == crs
    pytest.importorskip("rioxarray", reason="rioxarray is optional; the CF attributes are checked above")
    assert pyproj.CRS.from_wkt(dataset.rio.crs.to_wkt()).equals(crs, ignore_axis_order=True)  # what GDAL users see


def write_small_scan(path: Path, crs: pyproj.CRS | None) -> Path:
    """A 5,000-point LAS 1.4 patch, 60 units square, in `crs` (none when None), with two extra-bytes dimensions:
    a scaled integer `height` and a 3-element float `normal`."""
    header = laspy.LasHeader(version="1.4", point_format=6)
    header.scales, header.offsets = [0.001] * 3, [1_000.0, 2_000.0, 0.0]
    header.add_extra_dims([laspy.ExtraBytesParams("height", "i4", "height above ground", offsets=[0.1], scales=[0.01]),
                           laspy.ExtraBytesParams("normal", "3f8", "unit normal")])
    if crs is not None:
        header.add_crs(crs)
    las = laspy.LasData(header)
    rng = np.random.default_rng(5)
    xy = rng.uniform(0, 60, size=(5_000, 2))
    las.x, las.y, las.z = 1_000 + xy[:, 0], 2_000 + xy[:, 1], np.sin(xy[:, 0])
    las.height = np.round(rng.uniform(0, 30, 5_000), 2)
    las.normal = rng.normal(size=(5_000, 3))
    las.write(path)
    return path


def test_a_compound_crs_gives_z_its_vertical_unit(tmp_path):
    crs = pyproj.CRS("EPSG:2992+6360")  # Oregon Lambert in international feet + NAVD88 height in US survey feet
    store = tmp_path / "compound.zarr"
    pipeline.run(write_small_scan(tmp_path / "compound.las", crs), store, ratio=0.5, method="random", workers=1)
    dataset = open_quietly(store)
    assert dataset["x"].attrs["units"] == dataset["y"].attrs["units"] == "foot"
    assert dataset["z"].attrs["units"] == "US survey foot"
    assert pyproj.CRS.from_cf(dataset["spatial_ref"].attrs) == crs


def test_extra_bytes_keep_their_scale_and_elements(tmp_path):
    source = write_small_scan(tmp_path / "extra.las", None)
    store, las_path = tmp_path / "extra.zarr", tmp_path / "extra_out.las"
    for output in (store, las_path):
        pipeline.run(source, output, ratio=0.5, method="random", workers=1)
    dataset, las = open_quietly(store), laspy.read(las_path)
    assert dataset["normal"].dims == ("point", "normal_element") and dataset["normal"].shape == (2_500, 3)
    np.testing.assert_array_equal(dataset["normal"].values, np.asarray(las["normal"]))
    np.testing.assert_array_equal(dataset["height"].values, np.asarray(las["height"]))
    assert dataset["height"].attrs["long_name"] == "height above ground"
    assert dataset["height"].attrs["las_scale_factor"] == 0.01
    assert dataset["height"].attrs["las_add_offset"] == 0.1
    integers = np.round((dataset["height"].values - 0.1) / 0.01)
    np.testing.assert_array_equal(integers, las.points.array["height"])  # the raw LAS integers


def test_without_a_crs_there_is_no_spatial_ref(tmp_path):
    store = tmp_path / "bare.zarr"
    pipeline.run(write_small_scan(tmp_path / "bare.las", None), store, ratio=0.5, method="random", workers=1)
    dataset = open_quietly(store)
    assert "spatial_ref" not in dataset.variables and dataset.attrs["crs_wkt"] is None
    assert not any("grid_mapping" in variable.attrs for variable in dataset.variables.values())
    assert "units" not in dataset["x"].attrs and "units" not in dataset["z"].attrs  # no CRS says what the unit is
    assert dataset["x"].attrs["axis"] == "X" and "standard_name" not in dataset["x"].attrs  # nor what x measures
    assert set(dataset["intensity"].coords) == {"x", "y", "z"}


def test_an_unparseable_crs_stays_text_without_spatial_ref(tmp_path):
    source = shared_file("edge-cases/warsaw_small.las")  # its WKT VLR holds text pyproj cannot parse
    store = tmp_path / "warsaw.zarr"
    pipeline.run(source, store, ratio=0.5, method="random", workers=1)
    dataset = open_quietly(store)
    assert dataset.attrs["crs_wkt"]  # the raw text, as the input has it
    assert "spatial_ref" not in dataset.variables and "grid_mapping" not in dataset["intensity"].attrs


def write_clashing_scan(path: Path, names: tuple[str, ...]) -> Path:
    """A 3,000-point LAS 1.4 patch in UTM 10N with a u2 extra-bytes dimension per name, the i-th holding 1000 * i
    plus the point's index, so every dimension's values differ from the others'."""
    header = laspy.LasHeader(point_format=3, version="1.4")
    header.add_extra_dims([laspy.ExtraBytesParams(name, "u2") for name in names])
    header.add_crs(pyproj.CRS.from_epsg(32610))
    las = laspy.LasData(header)
    rng = np.random.default_rng(7)
    las.x, las.y, las.z = rng.uniform(0, 60, 3_000), rng.uniform(0, 60, 3_000), rng.uniform(0, 2, 3_000)
    for i, name in enumerate(names):
        las[name] = 1_000 * i + np.arange(3_000, dtype=np.uint16)
    las.write(path)
    return path


def test_extra_bytes_named_like_the_writers_arrays_or_with_a_slash_survive(tmp_path):
    names = ("spatial_ref", "tile_count", "a/b")  # the grid mapping, a tile-index array, a zarr group separator
    source = write_clashing_scan(tmp_path / "clash.las", names)
    store, las_path = tmp_path / "clash.zarr", tmp_path / "clash_out.las"
    for output in (store, las_path):
        pipeline.run(source, output, ratio=0.5, method="random", workers=1)
    dataset, las = open_quietly(store), laspy.read(las_path)
    by_las_name = {variable.attrs.get("las_dimension"): key for key, variable in dataset.variables.items()}
    for name in names:
        assert name in by_las_name, f"{name} is missing from {sorted(dataset.variables)}"
        variable = dataset[by_las_name[name]]
        assert variable.dims == ("point",) and "/" not in by_las_name[name]
        np.testing.assert_array_equal(variable.values, np.asarray(las[name]), err_msg=name)
    assert by_las_name["spatial_ref"] != "spatial_ref" and by_las_name["tile_count"] != "tile_count"
    assert pyproj.CRS.from_cf(dataset["spatial_ref"].attrs) == pyproj.CRS.from_epsg(32610)  # still the CRS
    assert dataset["tile_count"].dims == ("tile",) and int(dataset["tile_count"].sum()) == dataset.sizes["point"]


def test_every_extra_bytes_field_is_a_variable_by_its_own_name(tmp_path):
    """The second extra-bytes VLR's field (`confidence`), which laspy reads as one unnamed `ExtraBytes` byte, is
    a variable under its own name, holding the kept points' values."""
    from tests.test_copc import two_extra_bytes_vlrs

    source = two_extra_bytes_vlrs(6)
    source.write(tmp_path / "in.las")
    pipeline.run(tmp_path / "in.las", tmp_path / "out.zarr", ratio=0.5, method="random", workers=1)
    dataset = xr.open_zarr(tmp_path / "out.zarr")
    assert "confidence" in dataset and "ExtraBytes" not in dataset
    assert dataset["confidence"].attrs["long_name"] == "confidence values" and dataset["confidence"].dtype == np.uint8
    by_time = dict(zip(np.asarray(source.gps_time).astype(int), np.asarray(source.confidence)))
    kept = dataset["gps_time"].values.astype(int)
    assert np.array_equal(dataset["confidence"].values, [by_time[t] for t in kept])
    assert np.array_equal(dataset["Deviation"].values, np.asarray(source.Deviation)[kept])
