"""CF attributes of the zarr output's variables: what each LAS dimension means and its units, the tile index's
columns, and the CRS as a grid-mapping variable, so xarray, cf_xarray and rioxarray users need not know LAS."""
from __future__ import annotations

from typing import Any

import laspy
import numpy as np
import pyproj

from pipeline.io.crs import axis_unit

GRID_MAPPING = "spatial_ref"  # the variable name rioxarray and GDAL look for
COORDINATES = ("x", "y", "z")
TILE_BOUNDS = ("tile_xmin", "tile_ymin", "tile_xmax", "tile_ymax")
TILE_COLUMNS = (*TILE_BOUNDS, "tile_start", "tile_count")  # along `tile`, beside the tile id `tile` itself

# ASPRS LAS 1.4 R15 standard point classes; the codes left out (8, 12, 23-63) are reserved, 64-255 user-defined
ASPRS_CLASSES: dict[int, str] = {
    0: "created_never_classified", 1: "unclassified", 2: "ground", 3: "low_vegetation", 4: "medium_vegetation",
    5: "high_vegetation", 6: "building", 7: "low_point_noise", 9: "water", 10: "rail", 11: "road_surface",
    13: "wire_guard_shield", 14: "wire_conductor_phase", 15: "transmission_tower",
    16: "wire_structure_connector_insulator", 17: "bridge_deck", 18: "high_noise", 19: "overhead_structure",
    20: "ignored_ground", 21: "snow", 22: "temporal_exclusion",
}

_FLAG = {"flag_values": [0, 1], "flag_meanings": "false true"}
_GPS_TIME = {laspy.header.GpsTimeType.WEEK_TIME: "GPS week time (seconds since the start of the GPS week)",
             laspy.header.GpsTimeType.STANDARD: "adjusted standard GPS time (GPS seconds minus 1e9)"}

# What the LAS 1.4 specification says each standard dimension is; units only where it gives one
_DIMENSIONS: dict[str, dict[str, Any]] = {
    "x": {"long_name": "x coordinate (easting)"},
    "y": {"long_name": "y coordinate (northing)"},
    "z": {"long_name": "z coordinate (elevation)"},
    "intensity": {"long_name": "pulse return magnitude (intensity)"},
    "return_number": {"long_name": "return number of the point within its pulse"},
    "number_of_returns": {"long_name": "number of returns of the point's pulse"},
    "scan_direction_flag": {"long_name": "scan direction of the mirror", "flag_values": [0, 1],
                            "flag_meanings": "negative positive"},
    "edge_of_flight_line": {"long_name": "last point of a scan line before it changes direction", **_FLAG},
    "classification": {"long_name": "ASPRS point class", "flag_values": list(ASPRS_CLASSES),
                       "flag_meanings": " ".join(ASPRS_CLASSES.values())},
    "synthetic": {"long_name": "created by a technique other than LiDAR collection", **_FLAG},
    "key_point": {"long_name": "model key-point (not to be thinned away)", **_FLAG},
    "withheld": {"long_name": "withheld (to be ignored)", **_FLAG},
    "overlap": {"long_name": "within the overlap of two or more swaths", **_FLAG},
    "scanner_channel": {"long_name": "channel (scanner head) of a multi-channel system"},
    "scan_angle_rank": {"long_name": "scan angle, rounded to whole degrees", "units": "degree"},
    "scan_angle": {"long_name": "scan angle", "units": "0.006 degree"},  # raw LAS integers, 0.006 degree each
    "user_data": {"long_name": "user data"},
    "point_source_id": {"long_name": "source (flight line or file) the point came from"},
    "gps_time": {"units": "s"},  # long_name from the header's GPS time type
    "red": {"long_name": "red image channel"},
    "green": {"long_name": "green image channel"},
    "blue": {"long_name": "blue image channel"},
    "nir": {"long_name": "near-infrared image channel"},
    "wavepacket_index": {"long_name": "waveform packet descriptor index"},
    "wavepacket_offset": {"long_name": "offset of the waveform data", "units": "byte"},
    "wavepacket_size": {"long_name": "size of the waveform data", "units": "byte"},
    "return_point_wave_location": {"long_name": "return point location within the waveform", "units": "ps"},
    "x_t": {"long_name": "waveform line direction, x(t)"},
    "y_t": {"long_name": "waveform line direction, y(t)"},
    "z_t": {"long_name": "waveform line direction, z(t)"},
}
_TILES: dict[str, dict[str, Any]] = {
    "tile": {"long_name": "tile id"},
    "tile_start": {"long_name": "index along point of the tile's first point"},
    "tile_count": {"long_name": "points of the tile, stored contiguously from tile_start"},
    **{name: {"long_name": f"tile bounds: {name[5:]}"} for name in TILE_BOUNDS},
}


def point_attrs(name: str, header: laspy.LasHeader, crs: pyproj.CRS | None) -> dict[str, Any]:
    """Attributes of the point variable `name` (x, y, z or a LAS dimension): its LAS dimension, long name,
    units, flags and the scale/offset that turn float values back into the LAS integers."""
    las_name = name.upper() if name in COORDINATES else name
    info = header.point_format.dimension_by_name(las_name)
    attrs: dict[str, Any] = {"las_dimension": las_name, "long_name": info.description or name.replace("_", " ")}
    attrs.update(_DIMENSIONS.get(name, {}) if info.is_standard else {})
    if name in COORDINATES:
        axis = COORDINATES.index(name)
        scale, offset = float(header.scales[axis]), float(header.offsets[axis])
        attrs.update(las_scale_factor=scale, las_add_offset=offset,
                     comment=f"LAS integer {las_name} = round(({name} - las_add_offset) / las_scale_factor)")
        unit = axis_unit(crs, name)
        attrs.update({"units": unit} if unit else {})
        attrs.update(coordinate_role(name, crs))
    elif info.scales is not None:  # an extra-bytes dimension laspy scales (laspy requires offsets with scales)
        attrs.update(las_scale_factor=_json(info.scales), las_add_offset=_json(info.offsets))
    if name in ("return_number", "number_of_returns"):
        attrs["valid_range"] = [1, 2 ** info.num_bits - 1]
    if name == "gps_time":
        attrs["long_name"] = _GPS_TIME[header.global_encoding.gps_time_type]
    return attrs


def coordinate_role(name: str, crs: pyproj.CRS | None) -> dict[str, str]:
    """CF's axis of coordinate `name` (x, y or z), and for x and y in a projected CRS their standard name, which
    GDAL and cf_xarray read (not longitude and latitude for a geographic one: a geographic label also comes on
    coordinates in metres, as lone-star.laz's, which a run takes as metres)."""
    role = {"axis": name.upper(), **({"positive": "up"} if name == "z" else {})}
    horizontal = crs.sub_crs_list[0] if crs is not None and crs.is_compound else crs
    if horizontal is None or name == "z" or not horizontal.is_projected:
        return role
    return {**role, "standard_name": f"projection_{name}_coordinate"}


def tile_attrs(name: str, crs: pyproj.CRS | None) -> dict[str, Any]:
    """Attributes of a tile-index variable: its long name, and the horizontal unit for bounds."""
    unit = axis_unit(crs, name[5]) if name in TILE_BOUNDS else None
    return {**_TILES[name], **({"units": unit} if unit else {})}


def grid_mapping_attrs(crs: pyproj.CRS) -> dict[str, Any]:
    """Attributes of the 0-d `spatial_ref` variable: pyproj's CF grid mapping (with the WKT as CF's `crs_wkt`)
    and the WKT again as `spatial_ref`, where GDAL and rioxarray read it."""
    cf = crs.to_cf()
    return {**cf, "spatial_ref": cf["crs_wkt"]}


def _json(values: np.ndarray) -> float | list[float]:
    """An extra-bytes scale or offset as JSON: one number, or one per element of an array dimension."""
    return float(values[0]) if len(values) == 1 else [float(v) for v in values]
