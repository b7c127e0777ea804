"""Every LAS point format and version in, the same format, header and records out (generated files)."""
from __future__ import annotations

import laspy
import numpy as np
import pytest

import pipeline

VERSION_OF_FORMAT = {0: "1.2", 1: "1.0", 2: "1.1", 3: "1.2", 4: "1.3", 5: "1.3",
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
    source = random_scan(point_format)
    source_path = tmp_path / "in.laz"
    source.write(source_path)
    out = tmp_path / "out.laz"
    pipeline.run(source_path, out, ratio=0.3, workers=1, tile_size=10)
    result = laspy.read(out)
    assert result.header.version == VERSION_OF_FORMAT[point_format]
    assert result.header.point_format.id == point_format
    assert len(result.points) == 900
    rows = lambda a: np.ascontiguousarray(a).view(np.dtype((np.void, a.dtype.itemsize)))  # noqa: E731
    assert np.isin(rows(result.points.array), rows(laspy.read(source_path).points.array)).all()


def test_evlrs_survive(tmp_path):
    source = random_scan(6)
    source.header.evlrs = [laspy.VLR(user_id="survey", record_id=7, description="note", record_data=b"x" * 70_000)]
    source_path = tmp_path / "evlr.las"
    source.write(source_path)
    pipeline.run(source_path, tmp_path / "out.las", ratio=0.5, workers=1)
    evlrs = laspy.read(tmp_path / "out.las").header.evlrs
    assert [(v.user_id, v.record_id, bytes(v.record_data)) for v in evlrs] == [("survey", 7, b"x" * 70_000)]
