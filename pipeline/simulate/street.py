"""The simulated street's fixed layout: the labels and parts a point can carry, the scanner and its drive, the
cross-section of road, kerbs and sidewalks, the utility line, and the materials surfaces are made of."""
from __future__ import annotations

from datetime import date

import numpy as np

#: Street origin (x, y, z) in EPSG:26917 metres; also the LAS offsets.
ORIGIN = (630000.0, 4833000.0, 80.0)
EPSG = 26917
#: Toronto3D-style semantic labels stored in user_data.
LABELS = {0: "unclassified", 1: "road", 2: "road_marking", 3: "natural", 4: "building",
          5: "utility_line", 6: "pole", 7: "car"}
#: Finer parts of some surfaces (0: none, the label says it all), known to the simulator only: surface_parts().
PARTS = {1: "kerb", 2: "window", 3: "sign"}

SCALE = 0.001
CREATION_DATE = date(2020, 6, 1)  # fixed so that files are byte-reproducible
GPS_T0 = 400_000.0                # GPS week seconds at the first pulse
POINT_SOURCE_ID = 1

# Scanner and drive.
LINE_RATE = 100.0      # scan lines (mirror turns) per second
PULSES = 1200          # pulses per line (0.3 deg steps over 360 deg)
TILT = np.radians(15.0)  # scan plane rotated about the vertical axis
TAN_TILT = float(np.tan(TILT))
SPEED = 10.0           # mean vehicle speed, m/s (36 km/h)
LANE_Y = -1.75         # vehicle drives in the right lane of a road along +x
SENSOR_H = 2.4         # scanner height above the road crown
# The airborne platform: the same profiler flown along the centreline, firing only towards the ground.
ALTITUDE = 80.0        # flying height above the road crown, m
AIR_SPEED = 20.0       # ground speed, m/s: 0.2 m between scan lines, 0.42 m between pulses at the nadir
AIR_SECTOR = 25.0      # pulses fired within this many degrees of the nadir: a 75 m swath, inside Y_MAX
MIN_RANGE, MAX_RANGE = 2.5, 120.0
LINES_PER_BLOCK = 50

# Street cross-section (y across, z up, metres relative to ORIGIN).
ROAD_HALF = 7.0
CROWN = 0.07
SLOPE = 0.02
KERB = 0.13
EDGE_Z = CROWN - SLOPE * ROAD_HALF
Y_MAX = 40.0           # lateral extent of the modelled world
TILE_LENGTH = 40.0            # scene tile length along x

# Streams of SeedSequence([seed, stream, index]).
DRIVE_STREAM, TILE_STREAM, BLOCK_STREAM = 0, 1, 2

PANE_SHARE, INSIDE_SHARE = 0.4, 0.3   # glass: return at pane / from inside / none
VEG_SEP = 0.6                  # minimum separation of returns of one pulse (m)

Material = tuple  # (classification, label, reflectance, r, g, b); None = no return


def material(cls: int, label: int, refl: float, rgb: tuple[float, float, float], part: int = 0) -> Material:
    """A surface's LAS class, label, reflectance, colour and part, as one hashable tuple."""
    return (cls, label, float(refl), float(rgb[0]), float(rgb[1]), float(rgb[2]), part)


ASPHALT = material(11, 1, 0.14, (72, 72, 75))
MARK_WHITE = material(11, 2, 0.65, (225, 225, 220))
MARK_YELLOW = material(11, 2, 0.55, (220, 180, 50))
SIDEWALK = material(2, 1, 0.35, (178, 172, 162))
KERB_FACE = material(2, 1, 0.40, (160, 158, 152), part=1)
GLASS = material(6, 4, 0.06, (45, 55, 65), part=2)
INTERIOR = material(6, 4, 0.18, (75, 65, 58), part=2)
CAR_GLASS = material(1, 7, 0.05, (30, 35, 42))
CAR_INSIDE = material(1, 7, 0.12, (40, 38, 36))
TYRE = material(1, 7, 0.05, (28, 28, 30))
POLE_METAL = material(1, 6, 0.40, (125, 125, 130))
POLE_WOOD = material(1, 6, 0.30, (105, 85, 62))
LAMP = material(1, 6, 0.55, (205, 205, 195))
WIRE = material(14, 5, 0.25, (40, 40, 40))
TRUNK = material(5, 3, 0.30, (92, 72, 52))
RAILING = material(6, 4, 0.30, (55, 55, 60))
SLAB = material(6, 4, 0.45, (180, 180, 175))
FACADES = ((0.35, (148, 72, 56)), (0.30, (112, 58, 46)), (0.50, (205, 190, 160)),
            (0.45, (150, 150, 148)), (0.60, (225, 222, 214)), (0.22, (72, 74, 80)))
PAINTS = ((230, 230, 232), (25, 25, 28), (150, 152, 158), (110, 20, 25), (30, 50, 110),
           (200, 200, 195), (70, 75, 70))
SIGNS = ((20, 110, 60), (200, 30, 30), (30, 70, 160), (235, 235, 235))


def tint(rng: np.random.Generator, rgb: tuple[float, ...], spread: float = 0.08) -> tuple[float, ...]:
    """`rgb` with each channel scaled by a random factor around 1 (clipped to 0..255)."""
    return tuple(float(np.clip(v * (1.0 + rng.normal(0, spread)), 0, 255)) for v in rgb)


def stream_rng(seed: int, stream: int, index: int) -> np.random.Generator:
    """Independent generator for (seed, stream, index); index may be negative."""
    zigzag = 2 * index if index >= 0 else -2 * index - 1
    return np.random.default_rng(np.random.SeedSequence([seed, stream, zigzag]))


# Utility line on the left sidewalk: wooden poles mid-tile, three sagging wires.
UTIL_Y = 7.8
UTIL_H = 9.6
WIRES = ((UTIL_Y - 0.7, 0.0), (UTIL_Y + 0.7, 0.0), (UTIL_Y, 0.7))  # (y, dz at the pole)


def wire_height(x: np.ndarray) -> np.ndarray:
    """Height of the wire base line at x: catenary-like sag between poles at 40 t + 20."""
    u = (np.mod(x - 0.5 * TILE_LENGTH, TILE_LENGTH) - 0.5 * TILE_LENGTH) / (0.5 * TILE_LENGTH)
    return UTIL_H - 0.9 * (1.0 - u * u)
