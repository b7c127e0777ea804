"""The scan's coordinate reference system as WKT, from its LAS VLRs (pyproj when it can parse them)."""
from __future__ import annotations

import laspy


def crs_wkt(header: laspy.LasHeader) -> str | None:
    """WKT of the header's CRS, the raw WKT VLR text if pyproj cannot parse it, or None without one."""
    try:
        crs = header.parse_crs()
    except Exception:  # an unparseable WKT (e.g. warsaw_small.las) must not stop the run
        crs = None
    if crs is not None and crs.to_wkt():
        return crs.to_wkt()
    for vlr in header.vlrs:
        if isinstance(vlr, laspy.vlrs.known.WktCoordinateSystemVlr) and vlr.string:
            return vlr.string.strip("\x00")
    return None
