"""The simulated scan written as LAS 1.2 point format 3 (mm scale, EPSG:26917 GeoKeys), chunk by chunk,
through a temporary name; and the finer surface part of every point, which the file does not hold."""
from __future__ import annotations

import os
from pathlib import Path

import laspy
import numpy as np

from pipeline.io.atomic import atomic_output
from pipeline.simulate.raycast import PLATFORMS, Block, scan_blocks
from pipeline.simulate.street import CREATION_DATE, EPSG, ORIGIN, POINT_SOURCE_ID, SCALE


def street_header() -> laspy.LasHeader:
    """LAS 1.2 point format 3, mm scale, offsets at ORIGIN, a fixed date and the EPSG:26917 GeoKeys."""
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales = np.array([SCALE] * 3)
    header.offsets = np.array(ORIGIN)
    header.creation_date = CREATION_DATE
    header.system_identifier = "SIMULATION"
    header.generating_software = "pipeline.simulate"
    geo = laspy.vlrs.known.GeoKeyDirectoryVlr()
    geo.geo_keys = []
    # GTModelType=projected, GTRasterType=PixelIsArea, ProjectedCSType, linear/vertical units=metre
    for key_id, value in ((1024, 1), (1025, 1), (3072, EPSG), (3076, 9001), (4099, 9001)):
        geo.geo_keys.append(laspy.vlrs.known.GeoKeyEntryStruct(key_id, 0, 1, value))
    geo.geo_keys_header.number_of_keys = len(geo.geo_keys)
    header.vlrs.append(geo)
    return header


def point_record(parts: list[Block], header: laspy.LasHeader) -> laspy.ScaleAwarePointRecord:
    """The blocks' points as one record of `header`'s format (the surface part stays out of the file)."""
    n = sum(p["X"].size for p in parts)
    rec = laspy.ScaleAwarePointRecord.zeros(n, header=header)
    for key in parts[0].keys() - {"surface_part"}:
        col = np.concatenate([p[key] for p in parts])
        if key == "rgb":
            rec.red, rec.green, rec.blue = col[:, 0], col[:, 1], col[:, 2]
        else:
            rec[key] = col
    rec.point_source_id = np.full(n, POINT_SOURCE_ID, np.uint16)
    return rec


def surface_parts(n_points: int, seed: int = 0, platform: str = "mobile") -> np.ndarray:
    """(n_points,) uint8 part code (PARTS) of each point of write_street_scan(path, n_points, seed, platform=...),
    in file order: the scan is regenerated, so this costs about as long as writing it."""
    return np.concatenate([block["surface_part"] for block in scan_blocks(n_points, seed, platform)])


def write_street_scan(path: str | os.PathLike, n_points: int = 1_500_000, seed: int = 0,
                      chunk_points: int = 500_000, platform: str = "mobile") -> int:
    """Write a simulated LiDAR scan of the street, n_points points, to a LAS/LAZ file (by suffix); return the
    count written. `platform`: "mobile" (a car in the street, about 7.5 k points per metre of street) or
    "airborne" (an aircraft 80 m above it, about 830 points per metre: some 12 pulses per square metre).

    The count is exactly n_points; the street grows with n_points.  Same (n_points, seed, platform) gives a
    byte-identical file for any chunk_points, which only bounds how many points are held in memory before
    each write.  The file is written under a temporary name in the same folder and renamed when complete.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".las", ".laz"):
        raise ValueError(f"path must end in .las or .laz, got {path.name!r}")
    if n_points < 1 or chunk_points < 1 or seed < 0:
        raise ValueError("n_points and chunk_points must be >= 1 and seed >= 0")
    if platform not in PLATFORMS:
        raise ValueError(f"platform must be one of {sorted(PLATFORMS)}, got {platform!r}")
    header = street_header()
    written = 0
    with atomic_output(path) as temporary, \
            laspy.open(temporary, mode="w", header=header, do_compress=suffix == ".laz") as writer:
        pending: list[Block] = []
        held = 0
        for block in scan_blocks(n_points, seed, platform):
            pending.append(block)
            held += block["X"].size
            if held >= chunk_points:
                writer.write_points(point_record(pending, header))
                written += held
                pending, held = [], 0
        if pending:
            writer.write_points(point_record(pending, header))
            written += held
    return written
