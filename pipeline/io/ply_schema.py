"""How a PLY file's vertex properties become LAS 1.4 point format 7 dimensions.

Toronto3D's `scalar_*` properties and properties named as LAS dimensions (`intensity`, `gps_time`, PDAL's
`GpsTime`, ...) fill those dimensions, clipped to their ranges; colours of any PLY type fill LAS's 16-bit range;
every other property is kept as an extra-bytes dimension, renamed where its name is taken or too long for LAS
(32 bytes), with the PLY name in its description. Nothing a PLY holds per vertex is dropped.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Callable

import laspy
import numpy as np

from pipeline.errors import PipelineError

XYZ = ("x", "y", "z")
RGB = ("red", "green", "blue")
LAS_NAME_BYTES = 32
SCAN_ANGLE_STEP = 0.006  # degrees per unit of LAS 1.4's scan_angle
Converter = Callable[[np.ndarray], np.ndarray]


def clipped(dtype: str, low: int | None = None, high: int | None = None) -> Converter:
    """Rounded and clipped into an integer LAS dimension's range ([low, high] if narrower, for bit fields);
    NaN as 0."""
    info = np.iinfo(dtype)
    low, high = info.min if low is None else low, info.max if high is None else high
    return lambda v: np.clip(np.rint(finite(v)), low, high).astype(dtype)


def finite(values: np.ndarray) -> np.ndarray:
    """float64 values with NaN as 0 (and infinities as the float64 extremes, which the clips then bound)."""
    return np.nan_to_num(np.asarray(values, dtype=np.float64))


def degrees_to_scan_angle(values: np.ndarray) -> np.ndarray:
    """Scan angle in degrees to LAS 1.4's int16 steps of 0.006 degrees (+-180 degrees)."""
    return np.clip(np.rint(finite(values) / SCAN_ANGLE_STEP), -30000, 30000).astype(np.int16)


def as_float64(values: np.ndarray) -> np.ndarray:
    return np.asarray(values, dtype=np.float64)


TORONTO3D = {  # Toronto3D's property -> (LAS dimension, converter)
    "scalar_Intensity": ("intensity", clipped("u2")),
    "scalar_GPSTime": ("gps_time", as_float64),
    "scalar_ScanAngleRank": ("scan_angle", degrees_to_scan_angle),
    "scalar_Label": ("classification", clipped("u1")),
}
STANDARD = {  # a property named as a LAS dimension (lower case, underscores dropped: PDAL's names too)
    "intensity": ("intensity", clipped("u2")),
    "classification": ("classification", clipped("u1")),
    "gpstime": ("gps_time", as_float64),
    "returnnumber": ("return_number", clipped("u1", 0, 15)),
    "numberofreturns": ("number_of_returns", clipped("u1", 0, 15)),
    "userdata": ("user_data", clipped("u1")),
    "pointsourceid": ("point_source_id", clipped("u2")),
    "scananglerank": ("scan_angle", degrees_to_scan_angle),
}


def mapped_dimension(name: str) -> tuple[str, Converter] | None:
    """The LAS dimension a PLY property fills, and how, or None if it is kept as extra bytes."""
    return TORONTO3D.get(name) or STANDARD.get(name.lower().replace("_", ""))


def colour_converter(dtype: np.dtype, peak: float) -> Converter:
    """A PLY colour channel to LAS's 16-bit range: 8-bit integers x257 (255 -> 65535), wider integers as they
    are, floats by their range (`peak`, the channel's largest value): 0-1 x65535, 0-255 x257, else as they are;
    anything past 0-65535 clipped."""
    if dtype.kind in "ui":
        factor = 257.0 if dtype.itemsize == 1 else 1.0
    else:
        factor = 65535.0 if peak <= 1.0 else 257.0 if peak <= 255.0 else 1.0
    return lambda v: np.clip(np.rint(finite(v) * factor), 0, 65535).astype(np.uint16)


def extra_name(name: str, taken: set[str]) -> str:
    """A LAS extra-bytes name for a PLY property: its own if free and short enough, else `ply_` and its ASCII
    letters, digits and underscores, cut to 32 bytes and numbered until unique."""
    if name.isascii() and len(name) <= LAS_NAME_BYTES and name not in taken and name.lower() not in XYZ:
        return name
    stem = ("ply_" + re.sub(r"[^0-9A-Za-z_]", "_", name))[:LAS_NAME_BYTES]
    candidate, number = stem, 1
    while candidate in taken:
        number += 1
        suffix = f"_{number}"
        candidate = stem[: LAS_NAME_BYTES - len(suffix)] + suffix
    return candidate


@dataclass(frozen=True)
class PlySchema:
    """Where each vertex property goes: `mapped` (property, LAS dimension, converter), `extras` (property, LAS
    extra-bytes name, dtype) and `colours` (the RGB channels present); `default_returns`: the PLY says nothing
    of returns, so each point is written as the single return of its pulse (LAS 1.4 requires return 1 or more)."""

    mapped: tuple[tuple[str, str, Converter], ...]
    extras: tuple[tuple[str, str, np.dtype], ...]
    colours: tuple[str, ...]
    default_returns: bool

    @classmethod
    def of(cls, vertex_dtype: np.dtype, source: str) -> "PlySchema":
        """The schema of a PLY vertex element's record dtype (`source` names the file in errors)."""
        names = list(vertex_dtype.names or ())
        if not set(XYZ) <= set(names):
            raise PipelineError(f"{source}: PLY vertices lack x, y, z properties")
        taken = set(laspy.PointFormat(7).dimension_names)
        filled: set[str] = set()
        mapped, extras = [], []
        for name in names:
            if name in XYZ or name in RGB:
                continue
            dtype = vertex_dtype[name]
            if dtype.kind not in "uif" or dtype.shape:
                raise PipelineError(f"{source}: PLY vertex property {name!r} is a list or not a number; LAS "
                                    "cannot hold it (remove it, e.g. in CloudCompare, and run again)")
            target = mapped_dimension(name)
            if target is not None and target[0] not in filled:
                filled.add(target[0])
                mapped.append((name, *target))
                continue
            las_name = extra_name(name, taken)
            taken.add(las_name)
            extras.append((name, las_name, dtype.newbyteorder("=")))
        colours = tuple(c for c in RGB if c in names)
        return cls(tuple(mapped), tuple(extras), colours,
                   not filled & {"return_number", "number_of_returns"})
