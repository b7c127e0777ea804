"""Outputs say what made them: the header names lidar-simplify and today, a VLR and a zarr attribute hold
the run record as JSON, and simplifying an output again replaces its record instead of stacking them."""
from __future__ import annotations

import datetime
import json
from importlib.metadata import version

import laspy
import zarr

import pipeline
from pipeline.io.provenance import PROVENANCE_USER_ID, read_provenance
from tests.test_units import write_patch


def test_outputs_carry_the_run_record(tmp_path):
    write_patch(tmp_path / "ft.las", 2992, 0.3048, n=8_000)
    pipeline.run(tmp_path / "ft.las", tmp_path / "a.laz", ratio=0.2, method="fps", tile_size=20.0, workers=1)
    header = laspy.open(tmp_path / "a.laz").header
    assert header.generating_software == f"lidar-simplify {version('lidar-simplify')}"
    assert header.creation_date == datetime.date.today()
    vlr = next(v for v in header.vlrs if v.user_id == PROVENANCE_USER_ID)
    record = json.loads(bytes(vlr.record_data))
    assert record["method"] == "fps" and record["ratio"] == 0.2 and record["model_weights"] is None
    assert record["settings"]["tile_size"] == 20.0 and "workers" not in record["settings"]  # metres, as given
    assert record["sources"] == [str(tmp_path / "ft.las")]
    assert header.parse_crs().to_epsg() == 2992  # the input's CRS records stay

    pipeline.run(tmp_path / "a.laz", tmp_path / "b.laz", ratio=0.5, method="learned", workers=1)
    again = laspy.open(tmp_path / "b.laz").header
    assert sum(v.user_id == PROVENANCE_USER_ID for v in again.vlrs) == 1
    record = read_provenance(again)
    assert record["method"] == "learned" and record["model_weights"].startswith("detail.npz:")
    from pipeline.apps.scan_summary import format_summary, summarize
    said = format_summary(summarize(tmp_path / "b.laz", count_points=False)).splitlines()[-1]
    assert f"with learned (weights {record['model_weights']}) at ratio 0.5" in said  # the digest, not only in --json

    pipeline.run(tmp_path / "ft.las", tmp_path / "c.zarr", ratio=0.2, method="fps", workers=1)
    stored = zarr.open_group(str(tmp_path / "c.zarr"), mode="r").attrs["provenance"]
    assert stored["method"] == "fps" and stored["version"] == version("lidar-simplify")
