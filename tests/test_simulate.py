"""Tests for pipeline.simulate: counts, determinism, scene content, geometry, atomic writes."""

import laspy
import numpy as np
import pytest

from pipeline.simulate import ORIGIN, write_street_scan, writing


@pytest.fixture(scope="module")
def scan(tmp_path_factory):
    """A 200 k point scan (about 25 m of street) shared by the content tests."""
    path = tmp_path_factory.mktemp("scan") / "street.laz"
    count = write_street_scan(path, n_points=200_000, seed=0)
    return count, laspy.read(path)


def local_xyz(las):
    h = las.header
    return (np.asarray(las.x) - h.offsets[0], np.asarray(las.y) - h.offsets[1],
            np.asarray(las.z) - h.offsets[2])


@pytest.mark.parametrize("n", [20_000, 123_457])
def test_count_matches_request_and_header(tmp_path, n):
    path = tmp_path / "s.laz"
    count = write_street_scan(path, n_points=n, seed=1)
    las = laspy.read(path)
    assert count == n == las.header.point_count == len(las.points)


def test_header_bounds_crs_and_format(scan):
    _, las = scan
    h = las.header
    assert (h.version.major, h.version.minor, h.point_format.id) == (1, 2, 3)
    np.testing.assert_allclose(h.scales, 0.001)
    np.testing.assert_allclose(h.offsets, ORIGIN)
    xyz = np.stack([las.x, las.y, las.z])
    np.testing.assert_allclose(h.mins, xyz.min(1), atol=1e-6)
    np.testing.assert_allclose(h.maxs, xyz.max(1), atol=1e-6)
    keys = {k.id: k.value_offset for k in h.vlrs.get("GeoKeyDirectoryVlr")[0].geo_keys}
    assert keys[3072] == 26917 and keys[1024] == 1
    counts = np.bincount(np.asarray(las.return_number), minlength=6)[1:6]
    np.testing.assert_array_equal(h.number_of_points_by_return[:5], counts)


def test_same_seed_is_byte_identical_for_any_chunking(tmp_path):
    a, b, c = tmp_path / "a.laz", tmp_path / "b.laz", tmp_path / "c.laz"
    write_street_scan(a, n_points=150_000, seed=7, chunk_points=500_000)
    write_street_scan(b, n_points=150_000, seed=7, chunk_points=500_000)
    write_street_scan(c, n_points=150_000, seed=7, chunk_points=20_000)
    assert a.read_bytes() == b.read_bytes()
    assert a.read_bytes() == c.read_bytes()


def test_las_and_laz_hold_the_same_points(tmp_path):
    write_street_scan(tmp_path / "s.las", n_points=30_000, seed=2)
    write_street_scan(tmp_path / "s.laz", n_points=30_000, seed=2, chunk_points=7_000)
    las, laz = laspy.read(tmp_path / "s.las"), laspy.read(tmp_path / "s.laz")
    assert las.header.are_points_compressed is False and laz.header.are_points_compressed
    assert np.array_equal(las.points.array, laz.points.array)


def test_different_seed_gives_different_points(tmp_path):
    write_street_scan(tmp_path / "a.laz", n_points=50_000, seed=0)
    write_street_scan(tmp_path / "b.laz", n_points=50_000, seed=1)
    a, b = laspy.read(tmp_path / "a.laz"), laspy.read(tmp_path / "b.laz")
    assert not np.array_equal(np.asarray(a.X), np.asarray(b.X))
    assert not np.array_equal(np.asarray(a.classification), np.asarray(b.classification))


def test_scene_has_its_parts(scan):
    count, las = scan
    cls = set(np.unique(np.asarray(las.classification)).tolist())
    assert {2, 5, 6, 11} <= cls
    labels = set(np.unique(np.asarray(las.user_data)).tolist())
    assert {1, 2, 3, 4, 6, 7} <= labels  # road, marking, natural, building, pole, car
    ret, nret = np.asarray(las.return_number), np.asarray(las.number_of_returns)
    assert ret.max() > 1 and np.all(ret <= nret) and np.all(ret >= 1)
    veg = np.asarray(las.classification) == 5
    assert (nret[veg] > 1).mean() > 0.2          # crowns give multiple returns
    assert (nret[np.asarray(las.classification) == 6] == 1).mean() > 0.9  # solids: 1/1
    assert np.all(np.diff(np.asarray(las.gps_time)) >= 0)
    assert np.ptp(np.asarray(las.gps_time)) > 1.0
    assert np.asarray(las.intensity).std() > 1000
    for band in (las.red, las.green, las.blue):
        assert np.asarray(band).std() > 1000
    angle = np.asarray(las.scan_angle_rank)
    assert angle.min() < -45 and angle.max() > 45
    assert len(np.unique(np.asarray(las.point_source_id))) == 1


def test_multiple_returns_of_a_pulse_share_time_and_grow_in_range(scan):
    _, las = scan
    t, ret = np.asarray(las.gps_time), np.asarray(las.return_number)
    second = np.nonzero(ret == 2)[0]
    assert second.size > 100
    assert np.all(t[second] == t[second - 1]) and np.all(ret[second - 1] == 1)


def test_density_matches_a_mobile_scanner(scan):
    count, las = scan
    x, y, _ = local_xyz(las)
    metres = x.max() - x.min()
    assert 5_000 < count / metres < 12_000           # about 1.5 M points per 200 m
    road = np.asarray(las.classification) == 11
    near = road & (np.abs(y - (-1.75)) < 4)
    far = road & (np.abs(y - (-1.75)) > 6)
    # Points per square metre fall off with range from the trajectory.
    assert near.sum() / (8 * metres) > 2 * far.sum() / (2 * 3.25 * metres)


def test_road_kerb_and_sidewalk_heights(scan):
    _, las = scan
    x, y, z = local_xyz(las)
    cls = np.asarray(las.classification)
    road = cls == 11
    assert np.all(np.abs(z[road]) < 0.15)
    road_edge = np.median(z[road & (np.abs(y) > 6.2) & (np.abs(y) < 6.9)])
    walk_edge = np.median(z[(cls == 2) & (np.abs(y) > 7.1) & (np.abs(y) < 7.8)])
    assert 0.09 < walk_edge - road_edge < 0.17
    crown = np.median(z[road & (np.abs(y) < 1.0)])
    assert crown > road_edge + 0.08                   # cambered road


def facade_windows(las):
    """Building points of each 2 m stretch of each facade, with the modal facade plane y
    and the side (+1 left, -1 right); depth > 0 means behind the plane (inside)."""
    x, y, z = local_xyz(las)
    build = (np.asarray(las.classification) == 6) & (np.abs(y) > 9) & (z > 0.5) & (z < 12)
    for x0 in np.arange(np.floor(x.min()), x.max() - 2, 2.0):
        for side in (-1, 1):
            m = build & (x >= x0) & (x < x0 + 2) & (side * y > 0)
            if m.sum() < 200:
                continue
            yy = y[m]
            hist, edges = np.histogram(yy, bins=np.arange(yy.min(), yy.max() + 0.02, 0.02))
            plane = edges[np.argmax(hist)] + 0.01
            yield yy, z[m], plane, side * (yy - plane)


def test_facades_are_vertical_planes(scan):
    _, las = scan
    on_share = []
    for yy, zz, plane, _ in facade_windows(las):
        on = np.abs(yy - plane) < 0.05
        # The modal plane carries a good share of the points (the rest: reveals, panes,
        # rooms behind, balconies in front) and does not lean.
        assert on.mean() > 0.2
        low, high = on & (zz < np.median(zz[on])), on & (zz >= np.median(zz[on]))
        assert abs(np.median(yy[low]) - np.median(yy[high])) < 0.02
        on_share.append(on.mean())
    assert len(on_share) >= 8 and np.median(on_share) > 0.6


def test_windows_are_recessed(scan):
    _, las = scan
    recess = [np.mean((depth > 0.1) & (depth < 0.45)) for *_, depth in facade_windows(las)]
    # Window reveals and panes sit 0.1-0.45 m behind the facade plane.
    assert np.mean(recess) > 0.05 and max(recess) > 0.1


def test_no_temp_file_left_and_no_partial_file_on_error(tmp_path, monkeypatch):
    write_street_scan(tmp_path / "ok.laz", n_points=20_000, seed=0)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ok.laz"]

    def boom(*args, **kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr(writing, "point_record", boom)
    with pytest.raises(RuntimeError):
        write_street_scan(tmp_path / "bad.laz", n_points=20_000, seed=0)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ok.laz"]


def test_rejects_bad_arguments(tmp_path):
    with pytest.raises(ValueError):
        write_street_scan(tmp_path / "s.xyz", n_points=1000)
    with pytest.raises(ValueError):
        write_street_scan(tmp_path / "s.laz", n_points=0)
    with pytest.raises(ValueError, match="platform"):
        write_street_scan(tmp_path / "s.laz", n_points=1000, platform="satellite")
    assert list(tmp_path.iterdir()) == []


def test_the_airborne_scan_sees_the_street_from_above(tmp_path):
    """Flown over at 80 m within 25 degrees of the nadir: exact count, byte-identical for any chunking, scan
    angles within the sector, every point below the aircraft, roofs (building points well above the road) and
    car tops seen, the swath inside the modelled world, the road under the flight line covered (the ground
    behind tall buildings lies in their shadow, as from one real flight line), and the same street (labels) as
    the car's scan; the mobile scan is unchanged by the option."""
    from pipeline.simulate import surface_parts

    a, b = tmp_path / "a.laz", tmp_path / "b.laz"
    assert write_street_scan(a, n_points=60_000, seed=3, platform="airborne") == 60_000
    write_street_scan(b, n_points=60_000, seed=3, platform="airborne", chunk_points=9_000)
    assert a.read_bytes() == b.read_bytes()
    las = laspy.read(a)
    x, y, z = local_xyz(las)
    angle = np.asarray(las.scan_angle_rank)
    assert len(las.points) == 60_000 and np.abs(angle).max() <= 25 and np.abs(angle).min() == 0
    assert z.max() < 70 and np.abs(y).max() < 40  # under the aircraft (80 m up), inside the world
    label = np.asarray(las.user_data)
    assert {1, 3, 4, 7} <= set(np.unique(label))  # road, trees, buildings, cars
    assert np.quantile(z[label == 4], 0.9) > 5  # most building returns are roofs, high above the road
    assert x.max() - x.min() > 60 and np.abs(y).max() > 30  # 830 points a metre of street; a 75 m swath
    road = (np.abs(y) < 6) & (x > x.min() + 5) & (x < x.max() - 5)  # the road under the flight line: no shadow
    cells = np.unique(np.floor(np.column_stack([x, y])[road] / 1.0), axis=0)
    assert len(cells) >= 0.95 * 12 * np.ptp(x[road])  # nearly every 1 m cell of it holds a return
    parts = surface_parts(60_000, seed=3, platform="airborne")
    assert len(parts) == 60_000 and (parts == 2).any() and (label[parts == 2] == 4).all()  # windows on buildings
    write_street_scan(tmp_path / "m.laz", n_points=20_000, seed=3)
    write_street_scan(tmp_path / "n.laz", n_points=20_000, seed=3, platform="mobile")
    assert (tmp_path / "m.laz").read_bytes() == (tmp_path / "n.laz").read_bytes()


def test_surface_parts_align_with_the_written_points(tmp_path):
    """Kerb, window and sign parts are found where their surfaces are: right classes and labels."""
    from pipeline.simulate import PARTS, surface_parts

    path = tmp_path / "s.las"
    write_street_scan(path, n_points=120_000, seed=2)
    las = laspy.read(path)
    parts = surface_parts(120_000, seed=2)
    assert len(parts) == len(las.points) and set(np.unique(parts)) <= {0, *PARTS}
    classification, label = np.asarray(las.classification), np.asarray(las.user_data)
    assert (parts == 1).any() and (classification[parts == 1] == 2).all()   # kerb: ground class 2
    assert (parts == 2).any() and (label[parts == 2] == 4).all()            # window: building label
    assert (label[parts == 3] == 6).all()                                     # sign plate: pole label
