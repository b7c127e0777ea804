"""The scan's coordinate reference system: its WKT from the LAS VLRs, whether it is in degrees, and the
length unit of its horizontal axes (lengths given in metres are converted to it)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import laspy
import numpy as np

if TYPE_CHECKING:
    import pyproj  # imported where a WKT is parsed: a scan without a CRS never needs it (pipeline.io.lean_laspy)

_AXIS_DIRECTIONS = {"x": ("east", "west"), "y": ("north", "south"), "z": ("up", "down")}
DEGREE_SCALE = 1e-5  # a grid step this fine (about 1 m in degrees is 1e-5) only makes sense for angles
_PARSED: dict[tuple[tuple[int, bytes], ...], pyproj.CRS | None] = {}  # a header's CRS records -> their parse
_PARSED_KEPT = 8


def parsed_crs(header: laspy.LasHeader) -> pyproj.CRS | None:
    """The header's CRS as pyproj reads it, or None without one or when it cannot be parsed. Parsed once
    per distinct set of CRS records: a run asks four times, and pyproj takes 0.03 s a parse."""
    records = [*header.vlrs, *(header.evlrs or [])]
    key = tuple((vlr.record_id, vlr.record_data_bytes()) for vlr in records if vlr.user_id == "LASF_Projection")
    if not key:
        return None
    if key not in _PARSED:
        if len(_PARSED) >= _PARSED_KEPT:
            _PARSED.clear()
        try:
            _PARSED[key] = header.parse_crs()
        except Exception:  # an unparseable WKT (e.g. warsaw_small.las) must not stop the run
            _PARSED[key] = None
    return _PARSED[key]


def crs_wkt(header: laspy.LasHeader) -> str | None:
    """WKT of the header's CRS, the raw WKT VLR text if pyproj cannot parse it, or None without one."""
    crs = parsed_crs(header)
    if crs is not None and crs.to_wkt():
        return crs.to_wkt()
    for vlr in header.vlrs:
        if isinstance(vlr, laspy.vlrs.known.WktCoordinateSystemVlr) and vlr.string:
            return vlr.string.strip("\x00")
    return None


def las_wkt(wkt: str) -> str:
    """`wkt` as a LAS 1.4 CRS record holds it: WKT1 as GDAL writes it (the record is OGC WKT1, as PDAL writes it
    and proj4js, copc.js's projection library, reads it; pyproj's default, WKT2, is for the zarr output), or `wkt`
    unchanged where pyproj cannot parse it or cannot express the CRS in WKT1 (a 3-D geographic CRS, EPSG:4979)."""
    import pyproj

    crs = crs_from_wkt(wkt)
    try:
        return crs.to_wkt("WKT1_GDAL") if crs is not None else wkt
    except pyproj.exceptions.CRSError:
        return wkt


def degrees_reason(header: laspy.LasHeader) -> str | None:
    """Why the coordinates are in degrees (a geographic CRS, or no CRS but lon/lat-looking values on a
    sub-metre-in-degrees grid), or None. Tile sizes, halos and neighbourhoods are in metres."""
    crs = parsed_crs(header)
    mins, maxs = np.asarray(header.mins, float), np.asarray(header.maxs, float)
    in_range = in_degree_range(header)
    if crs is not None:  # a geographic label on values no degree can take (lone-star: "WGS 84", UTM-sized) is wrong
        return f"its CRS {crs.name!r} is geographic (coordinates in degrees)" if crs.is_geographic and in_range else None
    if in_range and max(header.scales[0], header.scales[1]) <= DEGREE_SCALE:
        return (f"it has no CRS and its coordinates look like degrees (x {mins[0]:g}..{maxs[0]:g}, "
                f"y {mins[1]:g}..{maxs[1]:g}, scale {header.scales[0]:g})")
    return None


def in_degree_range(header: laspy.LasHeader) -> bool:
    """Whether the header's x and y bounds are longitudes and latitudes (within +-180 and +-90)."""
    mins, maxs = np.asarray(header.mins, float), np.asarray(header.maxs, float)
    return bool(mins[0] >= -180 and maxs[0] <= 180 and mins[1] >= -90 and maxs[1] <= 90)


def same_crs(first: laspy.LasHeader, second: laspy.LasHeader) -> bool:
    """Whether two headers place coordinates in one CRS (as pyproj compares them; raw WKT text where
    pyproj cannot parse it; two files without a CRS agree)."""
    a, b = parsed_crs(first), parsed_crs(second)
    if a is not None and b is not None:
        return a.equals(b, ignore_axis_order=True)
    return a is None and b is None and crs_wkt(first) == crs_wkt(second)


def crs_label(header: laspy.LasHeader) -> str:
    """A short name for a message: 'EPSG:2992 (NAD83 / Oregon GIC Lambert (ft))', a CRS name, or 'no CRS'."""
    crs = parsed_crs(header)
    if crs is None:
        return "an unparsed CRS" if crs_wkt(header) else "no CRS"
    code = declared_epsg(crs)
    return f"EPSG:{code} ({crs.name})" if code else repr(crs.name)


def declared_epsg(crs: pyproj.CRS) -> int | None:
    """The EPSG code the CRS itself declares (its WKT's ID or AUTHORITY), or None: not pyproj's `to_epsg`,
    which searches its database for a match when none is declared (0.15-0.2 s on autzen's ESRI WKT, a
    tenth of a small run, to find none)."""
    ident = crs.to_json_dict().get("id") or {}
    return int(ident["code"]) if ident.get("authority") == "EPSG" else None


@dataclass(frozen=True)
class LengthUnit:
    """The unit of a scan's horizontal coordinates: its name, metres per unit, and whether it was assumed
    (no CRS, an unparsed one, or a geographic one, whose degrees are taken as they are)."""

    name: str
    metres: float
    assumed: bool

    def of_metres(self, metres: float) -> float:
        """A length given in metres, in this unit."""
        return metres / self.metres

    @property
    def label(self) -> str:
        """The unit's name for a report, marked where it was assumed: 'US survey foot', 'metre (assumed)'."""
        return f"{self.name} (assumed)" if self.assumed else self.name


def length_unit(header: laspy.LasHeader) -> LengthUnit:
    """The header's horizontal length unit (see `crs_length_unit`); metres, assumed, where a geographic CRS
    labels values no degree can take (lone-star: "WGS 84" on UTM-sized coordinates), as the run treats them
    (degrees_reason), so `info` and `eval` say what the run did."""
    crs = parsed_crs(header)
    if crs is not None and crs.is_geographic and not in_degree_range(header):
        return LengthUnit("metre", 1.0, assumed=True)
    return crs_length_unit(crs)


def crs_length_unit(crs: pyproj.CRS | None) -> LengthUnit:
    """A CRS's horizontal length unit (pyproj's axis unit and conversion factor: metre, foot, US survey foot,
    ...); metres where there is no CRS or it gives no unit, and no conversion for degrees."""
    if crs is None:
        return LengthUnit("metre", 1.0, assumed=True)
    if crs.is_geographic:
        return LengthUnit("degree", 1.0, assumed=True)
    horizontal = [axis for axis in crs.axis_info if axis.direction.lower() in ("east", "north", "west", "south")]
    for axis in horizontal or crs.axis_info:
        if axis.unit_conversion_factor and axis.unit_name:
            return LengthUnit(axis.unit_name, float(axis.unit_conversion_factor), assumed=False)
    return LengthUnit("metre", 1.0, assumed=True)


def unit_note(unit: LengthUnit, crs_name: str) -> str | None:
    """The one line a run says about units: lengths converted to the scan's unit, or metres assumed
    (nothing for metres, or for degrees, which the degree check speaks about)."""
    if unit.name == "degree":
        return None
    if unit.assumed:
        return "the scan has no usable CRS: its coordinates are taken as metres"
    if unit.metres == 1.0:
        return None
    return (f"lengths are in metres and the scan is in {unit.name} ({crs_name}): --tile-size, --overlap and "
            f"--seam-tolerance are converted (1 m = {unit.of_metres(1.0):.4g} {unit.name})")


def crs_from_wkt(wkt: str | None) -> pyproj.CRS | None:
    """A CRS as pyproj reads its WKT (a zarr output's attribute), or None without one or when pyproj cannot parse it."""
    import pyproj

    try:
        return pyproj.CRS.from_wkt(wkt) if wkt else None
    except pyproj.exceptions.CRSError:
        return None


def axis_unit(crs: pyproj.CRS | None, axis: str) -> str | None:
    """pyproj's unit name ('metre', 'foot', 'US survey foot', 'degree') of the CRS axis along x, y or z
    (its sub-CRSs' too: a compound CRS's vertical part), or None where the CRS has no such axis."""
    for part in (crs, *crs.sub_crs_list) if crs is not None else ():
        for info in part.axis_info:
            if info.direction.lower() in _AXIS_DIRECTIONS[axis] and info.unit_name:
                return info.unit_name
    return None
