"""`--levels` writes nested outputs from one simplification; `--keep-class`/`--thin-class` keep some classes
whole and thin the rest to the ratio, with every method, across tiles and seams."""
from __future__ import annotations

import laspy
import numpy as np
import pytest
from click.testing import CliRunner

import pipeline
from model.rules import kept_count
from pipeline.apps.cli import cli
from pipeline.engine.classes import classification

WIRE, BUILDING, ROAD = 14, 6, 11


def record_set(records: np.ndarray) -> set[bytes]:
    """Every record, all attributes, as bytes (a point's identity in set comparisons)."""
    return set(map(bytes, np.ascontiguousarray(records).view(np.dtype((np.void, records.dtype.itemsize)))))


@pytest.mark.parametrize("method", ["fps", "learned"])
def test_levels_are_nested_exact_and_the_finest_is_the_plain_run(tmp_path, street_scan, method):
    settings = dict(method=method, tile_size=20.0, workers=1)
    report = pipeline.run(street_scan, tmp_path / "out.laz", levels=(0.2, 0.1, 0.05), **settings)
    paths = [tmp_path / f"out.r{r}.laz" for r in ("0.2", "0.1", "0.05")]
    assert [p for p, _ in report.levels] == paths and not (tmp_path / "out.laz").exists()
    kept = [laspy.read(p).points.array for p in paths]
    assert [len(k) for k in kept] == [kept_count(r, 60_000) for r in (0.2, 0.1, 0.05)]
    sets = [record_set(k) for k in kept]
    assert sets[1] <= sets[0] and sets[2] <= sets[1]
    plain = pipeline.run(street_scan, tmp_path / "plain.laz", ratio=0.2, **settings)
    assert np.array_equal(laspy.read(plain.output).points.array, kept[0])  # the same points, in the same order


def test_each_level_is_a_subset_of_the_one_before_when_tile_budgets_are_uneven(tmp_path):
    """Three levels over tiles of very unequal size (a crowded cell split among small tiles beside sparse ones):
    shared from the finest level each time, largest-remainder budgets are not monotone in their total, and the
    0.3 level held points the 0.4 level did not."""
    rng = np.random.default_rng(1)
    xyz = np.r_[rng.uniform(0, 1, (5_000, 3)) * [200, 200, 5], rng.normal(0, 0.05, (4_000, 3)) + [100, 100, 2]]
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales, header.offsets = [0.01] * 3, [0.0] * 3
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz.T
    las.gps_time = np.arange(len(xyz), dtype=np.float64)  # each point's id
    las.write(tmp_path / "in.las")
    pipeline.run(tmp_path / "in.las", tmp_path / "out.las", levels=(0.9, 0.4, 0.3), method="stratified",
                 max_tile_points=1_000, workers=1)
    ids = [set(laspy.read(tmp_path / f"out.r{level}.las").gps_time.astype(int)) for level in ("0.9", "0.4", "0.3")]
    assert [len(level) for level in ids] == [kept_count(r, 9_000) for r in (0.9, 0.4, 0.3)]
    assert ids[2] <= ids[1] <= ids[0]


def test_coarse_levels_stay_spread_over_the_scan(tmp_path, street_scan):
    """A level is each tile's first picks, not the first tiles: its points cover the scan's 10 m cells as the
    finest level's do."""
    pipeline.run(street_scan, tmp_path / "out.laz", levels=(0.2, 0.02), method="fps", tile_size=20.0, workers=1)
    fine, coarse = (laspy.read(tmp_path / f"out.r{r}.laz") for r in ("0.2", "0.02"))

    def cells(las: laspy.LasData) -> set[tuple[int, int]]:
        return set(map(tuple, np.floor(np.column_stack([las.x, las.y]) / 10).astype(int)))

    assert len(cells(coarse)) >= 0.9 * len(cells(fine))


@pytest.mark.parametrize("method", ["random", "fps", "learned"])
def test_keep_class_keeps_every_point_of_those_classes_with_every_attribute(tmp_path, street_scan, method):
    source = laspy.read(street_scan).points.array
    codes = classification(source)
    protected = np.isin(codes, (WIRE, BUILDING))
    report = pipeline.run(street_scan, tmp_path / "out.laz", ratio=0.1, keep_classes=(WIRE, BUILDING),
                          method=method, tile_size=20.0, workers=1)
    kept = laspy.read(tmp_path / "out.laz").points.array
    assert record_set(source[protected]) <= record_set(kept)
    thinned = len(kept) - int(protected.sum())
    assert thinned == kept_count(0.1, int((~protected).sum()))
    assert report.kept_whole == int(protected.sum()) and report.output_points == len(kept)
    assert len(record_set(kept)) == len(kept)  # no point twice, seams included


def test_thin_class_thins_only_those_classes_and_levels_keep_them_all(tmp_path, street_scan):
    source = laspy.read(street_scan).points.array
    road = classification(source) == ROAD
    pipeline.run(street_scan, tmp_path / "out.zarr", levels=(0.5, 0.1), thin_classes=(ROAD,), method="fps",
                 tile_size=20.0, workers=1)
    import zarr

    for ratio in ("0.5", "0.1"):
        group = zarr.open_group(str(tmp_path / f"out.r{ratio}.zarr"), mode="r")
        codes = np.asarray(group["classification"][:])
        assert (codes != ROAD).sum() == (~road).sum()
        assert (codes == ROAD).sum() == kept_count(float(ratio), int(road.sum()))


def test_the_cli_says_both_numbers_and_names_a_missing_class(tmp_path, street_scan):
    result = CliRunner().invoke(cli, ["run", str(street_scan), "--ratio", "0.1", "--keep-class", "14,9", "-m", "fps",
                                      "-w", "1", "-o", str(tmp_path / "out.laz")])
    assert result.exit_code == 0, result.output
    wire = int((classification(laspy.read(street_scan).points.array) == WIRE).sum())
    assert f"classes 14, 9 kept whole: {wire:,} points kept whole; the other {60_000 - wire:,} thinned to " \
           f"{kept_count(0.1, 60_000 - wire):,}" in result.stdout
    assert "note: class 9 has no points in the scan" in result.stderr


@pytest.mark.parametrize("args, words", [
    (["--levels", "0.1,0.2"], "--levels must decrease"),
    (["--levels", "0.2,0,0.1"], "--levels must be ratios in (0, 1]"),
    (["--levels", "0.2,abc"], "--levels takes comma-separated numbers"),
    (["--levels", "0.2,0.1", "--ratio", "0.1"], "disagrees with --levels"),
    (["--keep-class", "6", "--thin-class", "2", "-r", "0.1"], "not both"),
    (["--keep-class", "300", "-r", "0.1"], "codes 0-255"),
    ([], "give --ratio"),
])
def test_bad_levels_and_classes_get_one_line(tmp_path, street_scan, args, words):
    result = CliRunner().invoke(cli, ["run", str(street_scan), *args, "-o", str(tmp_path / "out.laz")])
    assert result.exit_code == 2 and words in result.stderr and len(result.stderr.strip().splitlines()) == 1
    assert list(tmp_path.iterdir()) == []


def test_a_run_that_fails_in_its_last_level_leaves_no_level_and_its_rerun_resumes(tmp_path, street_scan, monkeypatch):
    """A disk that fills while the last level is written: the levels written before it stayed in place, and the
    re-run the error line advises was refused ('already exists'). All levels now go in place at once, or none."""
    import errno

    from pipeline.io import writers

    write_las, calls = writers._write_las, []

    def full_disk_on_the_third(path, *args, **kwargs):
        calls.append(path)
        if len(calls) == 3:
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        return write_las(path, *args, **kwargs)

    settings = dict(levels=(0.2, 0.1, 0.05), method="fps", workers=1)
    with monkeypatch.context() as patched:
        patched.setattr(writers, "_write_las", full_disk_on_the_third)
        with pytest.raises(pipeline.PipelineError, match=r"out\.r0\.05\.laz: No space left on device .*resume"):
            pipeline.run(street_scan, tmp_path / "out.laz", **settings)
    assert sorted(p.name for p in tmp_path.iterdir() if not p.name.startswith(".out.laz.work-")) == []
    report = pipeline.run(street_scan, tmp_path / "out.laz", **settings)  # the same command, as advised
    assert report.resumed_tiles > 0 and len(report.levels) == 3
