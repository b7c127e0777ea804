"""Deterministic mobile-LiDAR street-scan simulator, streamed to LAS/LAZ.

Why: the simplification pipeline needs realistic, reproducible test and benchmark
clouds of any size (10 k .. 30 M points) without shipping survey data.

How: a vehicle drives along the centreline of a Toronto3D-like street (road with
camber and markings, kerbs, sidewalks, facades with recessed windows and balconies,
street lights, sign poles, a utility line, parked cars, trees).  A rotating 2-D
profiler, tilted about the vertical axis, fires pulses that are ray-cast against
analytic primitives (planes, boxes, cylinders, spheres, ellipsoids), so density
falls off with range, scan lines show as stripes and occlusion is physical.
Tree crowns are semi-transparent and give up to three returns per pulse.

Everything is generated in blocks of scan lines whose random numbers depend only on
(seed, block index); the scene is generated in 40 m tiles that depend only on
(seed, tile index).  Blocks are written in order and trimmed at the end, so the
file is byte-identical for a given (n_points, seed) whatever chunk_points is, and
memory is bounded by chunk_points plus one block.

Output: LAS 1.2 point format 3, mm scale, offsets at the street origin
(UTM 17N / EPSG:26917 near Toronto, stored as a GeoTIFF GeoKeyDirectory VLR).
classification uses ASPRS codes (11 road, 2 sidewalk/kerb, 6 building,
5 vegetation, 14 wire, 1 cars/poles); user_data holds a Toronto3D-style label
(see LABELS) so cars and poles stay distinguishable; surface_parts() gives finer parts of
each point (see PARTS: kerb, window, sign) for per-object scoring, without changing the file.
"""

from __future__ import annotations

import os
import uuid
from datetime import date
from functools import lru_cache
from pathlib import Path

import laspy
import numpy as np

__all__ = ["write_street_scan", "surface_parts", "LABELS", "PARTS", "ORIGIN", "EPSG"]

#: Street origin (x, y, z) in EPSG:26917 metres; also the LAS offsets.
ORIGIN = (630000.0, 4833000.0, 80.0)
EPSG = 26917
#: Toronto3D-style semantic labels stored in user_data.
LABELS = {0: "unclassified", 1: "road", 2: "road_marking", 3: "natural", 4: "building",
          5: "utility_line", 6: "pole", 7: "car"}
#: Finer parts of some surfaces (0: none, the label says it all), known to the simulator only: surface_parts().
PARTS = {1: "kerb", 2: "window", 3: "sign"}

_SCALE = 0.001
_CREATION_DATE = date(2020, 6, 1)  # fixed so that files are byte-reproducible
_GPS_T0 = 400_000.0                # GPS week seconds at the first pulse
_POINT_SOURCE_ID = 1

# Scanner and drive.
_LINE_RATE = 100.0      # scan lines (mirror turns) per second
_PULSES = 1200          # pulses per line (0.3 deg steps over 360 deg)
_TILT = np.radians(15.0)  # scan plane rotated about the vertical axis
_TAN = float(np.tan(_TILT))
_SPEED = 10.0           # mean vehicle speed, m/s (36 km/h)
_LANE_Y = -1.75         # vehicle drives in the right lane of a road along +x
_SENSOR_H = 2.4         # scanner height above the road crown
_MIN_RANGE, _MAX_RANGE = 2.5, 120.0
_LINES_PER_BLOCK = 50

# Street cross-section (y across, z up, metres relative to ORIGIN).
_ROAD_HALF = 7.0
_CROWN = 0.07
_SLOPE = 0.02
_KERB = 0.13
_EDGE_Z = _CROWN - _SLOPE * _ROAD_HALF
_Y_MAX = 40.0           # lateral extent of the modelled world
_TILE = 40.0            # scene tile length along x

# Streams of SeedSequence([seed, stream, index]).
_DRIVE, _TILE_STREAM, _BLOCK_STREAM = 0, 1, 2

_P_GLASS, _P_INNER = 0.4, 0.3   # glass: return at pane / from inside / none
_VEG_SEP = 0.6                  # minimum separation of returns of one pulse (m)

_Surf = tuple  # (classification, label, reflectance, r, g, b); None = no return


# --------------------------------------------------------------------------- rays
class _Rays:
    """Rays of one scanner side in one block, sorted by key = x + tan(tilt) * y."""

    __slots__ = ("ox", "oy", "oz", "dx", "dy", "dz", "key")

    def __init__(self, ox, oy, oz, dx, dy, dz):
        self.ox, self.oy, self.oz, self.dx, self.dy, self.dz = ox, oy, oz, dx, dy, dz
        self.key = ox + _TAN * oy

    def take(self, sel) -> _Rays:
        """The rays selected by a slice, mask or index array."""
        return _Rays(self.ox[sel], self.oy[sel], self.oz[sel],
                     self.dx[sel], self.dy[sel], self.dz[sel])


class _Hits:
    """Nearest solid hit per ray: distance, normal and surface id (0 = no return)."""

    def __init__(self, n: int):
        self.t = np.full(n, np.inf)
        self.n = np.zeros((3, n))
        self.surf = np.zeros(n, np.int32)

    def offer(self, idx, t, normal, surf) -> None:
        """Keep (t, normal, surf) for rays idx where t is nearer than the current hit."""
        m = t < self.t[idx]
        if not m.any():
            return
        j = idx[m]
        self.t[j] = t[m]
        for a in range(3):
            self.n[a, j] = np.broadcast_to(normal[a], t.shape)[m]
        self.surf[j] = np.broadcast_to(surf, t.shape)[m]


class _Registry:
    """Maps surface descriptors to small ids for one block (id 0 = no return)."""

    def __init__(self):
        self.ids: dict = {None: 0}
        self.rows: list = [(0, 0, 0.0, 0.0, 0.0, 0.0, 0)]

    def __call__(self, surf: _Surf | None) -> int:
        if surf not in self.ids:
            self.ids[surf] = len(self.rows)
            self.rows.append(surf)
        return self.ids[surf]


def _krange(xlo, xhi, ylo, yhi):
    """Range of ray keys that can reach the box [xlo, xhi] x [ylo, yhi]."""
    return xlo + _TAN * ylo - 0.05, xhi + _TAN * yhi + 0.05


def _box_hit(r: _Rays, lo, hi):
    """Entry distance (inf = miss) and entry axis of rays into an axis-aligned box."""
    tn, tf = [], []
    for o, d, a, b in ((r.ox, r.dx, lo[0], hi[0]), (r.oy, r.dy, lo[1], hi[1]),
                       (r.oz, r.dz, lo[2], hi[2])):
        t0, t1 = (a - o) / d, (b - o) / d
        tn.append(np.minimum(t0, t1))
        tf.append(np.maximum(t0, t1))
    near = np.maximum(np.maximum(tn[0], tn[1]), tn[2])
    far = np.minimum(np.minimum(tf[0], tf[1]), tf[2])
    axis = np.where((tn[0] >= tn[1]) & (tn[0] >= tn[2]), 0, np.where(tn[1] >= tn[2], 1, 2))
    return np.where((near <= far) & (near > 0), near, np.inf), axis


def _axis_normal(r: _Rays, axis):
    """Outward normal of the box face crossed along `axis` (facing the ray)."""
    return tuple(np.where(axis == a, -np.sign(d), 0.0) for a, d in enumerate((r.dx, r.dy, r.dz)))


def _quad_in(px, py, ux, uy, rad):
    """Nearest positive root of |p + t u| = rad in 2-D (inf = miss)."""
    a = ux * ux + uy * uy
    b = px * ux + py * uy
    disc = b * b - a * (px * px + py * py - rad * rad)
    t = (-b - np.sqrt(np.maximum(disc, 0.0))) / a
    return np.where((disc > 0) & (t > 0), t, np.inf)


def _ellipsoid(r: _Rays, c, s):
    """Entry and exit distances of rays through an ellipsoid (centre c, semi-axes s)."""
    p = [(o - ci) / si for o, ci, si in zip((r.ox, r.oy, r.oz), c, s)]
    u = [d / si for d, si in zip((r.dx, r.dy, r.dz), s)]
    a = u[0] ** 2 + u[1] ** 2 + u[2] ** 2
    b = p[0] * u[0] + p[1] * u[1] + p[2] * u[2]
    disc = b * b - a * (p[0] ** 2 + p[1] ** 2 + p[2] ** 2 - 1.0)
    root = np.sqrt(np.maximum(disc, 0.0))
    ok = disc > 0
    return np.where(ok, (-b - root) / a, np.inf), np.where(ok, (-b + root) / a, -np.inf)


def _glass(t, extra, rng, glass: _Surf, inner: _Surf, reg: _Registry):
    """Split pulses reaching glass at t into pane returns, returns from `extra` behind it,
    and lost pulses (no return, but nothing behind is seen either)."""
    u = rng.random(t.size)
    t = t.copy()
    surf = np.full(t.size, reg(glass), np.int32)
    behind = (u >= _P_GLASS) & (u < _P_GLASS + _P_INNER)
    t[behind] += extra[behind]
    surf[behind] = reg(inner)
    surf[u >= _P_GLASS + _P_INNER] = 0
    return t, surf


# ----------------------------------------------------------------------- primitives
class _Prim:
    """A solid scene element on one side of the street (0 = right/-y, 1 = left/+y)."""

    side: int
    kmin: float
    kmax: float

    def cast(self, r: _Rays, idx, hits: _Hits, reg: _Registry, rng) -> None:
        raise NotImplementedError


class _Box(_Prim):
    """Axis-aligned solid box; `bars` makes it a railing (top rail + balusters along an axis)."""

    def __init__(self, side, lo, hi, surf, bars=None):
        self.side, self.lo, self.hi, self.surf, self.bars = side, lo, hi, surf, bars
        self.kmin, self.kmax = _krange(lo[0], hi[0], lo[1], hi[1])

    def cast(self, r, idx, hits, reg, rng):
        t, axis = _box_hit(r, self.lo, self.hi)
        if self.bars is not None:  # gaps between balusters below the top rail
            bar_axis, pitch = self.bars
            along = (r.ox, r.oy)[bar_axis] + t * (r.dx, r.dy)[bar_axis]
            z = r.oz + t * r.dz
            solid = (np.mod(along, pitch) < 0.03) | (z > self.hi[2] - 0.05)
            t = np.where(solid, t, np.inf)
        hits.offer(idx, t, _axis_normal(r, axis), reg(self.surf))


class _Building(_Prim):
    """Building block whose street facade has a grid of recessed glazed openings."""

    def __init__(self, side, x0, x1, yf, depth, height, wall, grid):
        s = 1 if side else -1
        self.side, self.s, self.yf, self.wall = side, s, s * yf, wall
        y_lo, y_hi = sorted((s * yf, s * (yf + depth)))
        self.lo, self.hi = (x0, y_lo, -0.5), (x1, y_hi, height)
        self.kmin, self.kmax = _krange(x0, x1, y_lo, y_hi)
        self.g = grid
        self.reveal = wall[:3] + tuple(0.85 * v for v in wall[3:])

    def cast(self, r, idx, hits, reg, rng):
        t, axis = _box_hit(r, self.lo, self.hi)
        got = np.nonzero(np.isfinite(t))[0]
        if got.size == 0:
            return
        rg, t, axis = r.take(got), t[got], axis[got]
        normal = _axis_normal(rg, axis)
        surf = np.full(got.size, reg(self.wall), np.int32)
        if self.g["ncol"]:
            self._openings(rg, t, normal, surf, axis == 1, reg, rng)
        hits.offer(idx[got], t, normal, surf)

    def _openings(self, r, t, normal, surf, facade, reg, rng) -> None:
        """Rays whose facade hit lies in an opening go on into the recess (in place)."""
        g = self.g
        f = np.nonzero(facade)[0]
        hx, hz = r.ox[f] + t[f] * r.dx[f], r.oz[f] + t[f] * r.dz[f]
        col = np.floor((hx - g["x_start"]) / g["px"])
        floor = np.where(hz < g["gf"], 0, 1 + np.floor((hz - g["gf"]) / g["fh"]))
        upper = floor > 0
        ww = np.where(upper, g["ww"], g["ww0"])
        wh = np.where(upper, g["wh"], g["wh0"])
        wx0 = g["x_start"] + col * g["px"] + np.where(upper, 0.0, (g["ww"] - g["ww0"]) / 2)
        wz0 = np.where(upper, g["gf"] + (floor - 1) * g["fh"] + g["sill"], g["sill0"])
        inside = ((col >= 0) & (col < g["ncol"]) & (floor <= g["nup"]) & (hx >= wx0)
                  & (hx < wx0 + ww) & (hz >= wz0) & (hz < wz0 + wh))
        w = f[inside]
        if w.size == 0:
            return
        rw = r.take(w)
        wx0, wz0, ww, wh = wx0[inside], wz0[inside], ww[inside], wh[inside]
        # Leave the recess through a reveal, or reach the pane at its back.
        tx = (np.where(rw.dx > 0, wx0 + ww, wx0) - rw.ox) / rw.dx
        tz = (np.where(rw.dz > 0, wz0 + wh, wz0) - rw.oz) / rw.dz
        ty = (self.yf + self.s * g["recess"] - rw.oy) / rw.dy
        pane = ty <= np.minimum(tx, tz)
        rev, via_x = w[~pane], (tx <= tz)[~pane]
        t[rev] = np.minimum(tx, tz)[~pane]
        normal[0][rev] = np.where(via_x, -np.sign(rw.dx[~pane]), 0.0)
        normal[1][rev] = 0.0
        normal[2][rev] = np.where(via_x, 0.0, -np.sign(rw.dz[~pane]))
        surf[rev] = reg(self.reveal)
        # Behind the pane: the room's back wall, floor or ceiling.
        tp, rp = ty[pane], rw.take(pane)
        base = np.where(upper[inside][pane], wz0[pane] - g["sill"], 0.0)
        ceiling = base + np.where(upper[inside][pane], g["fh"], g["gf"])
        zp = rp.oz + tp * rp.dz
        to_slab = np.where(rp.dz > 0, ceiling - zp, base - zp) / rp.dz
        extra = np.minimum(rng.uniform(1.0, 6.0, tp.size) / np.abs(rp.dy), to_slab)
        t[w[pane]], surf[w[pane]] = _glass(tp, extra, rng, _GLASS, _INTERIOR, reg)


class _VCyl(_Prim):
    """Vertical cylinder (pole, trunk)."""

    def __init__(self, side, cx, cy, rad, z0, z1, surf):
        self.side, self.c, self.rad, self.z, self.surf = side, (cx, cy), rad, (z0, z1), surf
        self.kmin, self.kmax = _krange(cx - rad, cx + rad, cy - rad, cy + rad)

    def cast(self, r, idx, hits, reg, rng):
        px, py = r.ox - self.c[0], r.oy - self.c[1]
        t = _quad_in(px, py, r.dx, r.dy, self.rad)
        z = r.oz + t * r.dz
        t = np.where((z >= self.z[0]) & (z <= self.z[1]), t, np.inf)
        fin = np.where(np.isfinite(t), t, 0.0)
        normal = ((px + fin * r.dx) / self.rad, (py + fin * r.dy) / self.rad, 0.0)
        hits.offer(idx, t, normal, reg(self.surf))


class _YCyl(_Prim):
    """Horizontal cylinder along y (lamp arm, wheel)."""

    def __init__(self, side, cx, cz, rad, y0, y1, surf):
        self.side, self.c, self.rad, self.y, self.surf = side, (cx, cz), rad, (y0, y1), surf
        self.kmin, self.kmax = _krange(cx - rad, cx + rad, y0, y1)

    def cast(self, r, idx, hits, reg, rng):
        px, pz = r.ox - self.c[0], r.oz - self.c[1]
        t = _quad_in(px, pz, r.dx, r.dz, self.rad)
        y = r.oy + t * r.dy
        t = np.where((y >= self.y[0]) & (y <= self.y[1]), t, np.inf)
        fin = np.where(np.isfinite(t), t, 0.0)
        normal = ((px + fin * r.dx) / self.rad, 0.0, (pz + fin * r.dz) / self.rad)
        hits.offer(idx, t, normal, reg(self.surf))


class _Cabin(_Prim):
    """Rounded car top: upper half of an ellipsoid, glazed above the belt line."""

    def __init__(self, side, c, s, paint):
        self.side, self.c, self.s, self.paint = side, c, s, paint
        self.kmin, self.kmax = _krange(c[0] - s[0], c[0] + s[0], c[1] - s[1], c[1] + s[1])

    def cast(self, r, idx, hits, reg, rng):
        t, _ = _ellipsoid(r, self.c, self.s)
        t = np.where(t > 0, t, np.inf)
        pts = [o + np.where(np.isfinite(t), t, 0.0) * d
               for o, d in ((r.ox, r.dx), (r.oy, r.dy), (r.oz, r.dz))]
        t = np.where(pts[2] >= self.c[2], t, np.inf)
        got = np.nonzero(np.isfinite(t))[0]
        if got.size == 0:
            return
        normal = [(pts[a][got] - self.c[a]) / self.s[a] ** 2 for a in range(3)]
        norm = np.sqrt(normal[0] ** 2 + normal[1] ** 2 + normal[2] ** 2)
        normal = tuple(v / norm for v in normal)
        glazed = pts[2][got] > self.c[2] + 0.12 * self.s[2]
        surf = np.full(got.size, reg(self.paint), np.int32)
        tg, dz = t[got][glazed], r.dz[got][glazed]
        # Behind the glass: seats or the far side, never below seat level.
        to_seat = np.where(dz < 0, (pts[2][got][glazed] - (self.c[2] - 0.4)) / -dz, np.inf)
        extra = np.minimum(rng.uniform(0.3, 1.5, tg.size), to_seat)
        tg, sg = _glass(tg, extra, rng, _CAR_GLASS, _CAR_INSIDE, reg)
        tt = t[got].copy()
        tt[glazed], surf[glazed] = tg, sg
        hits.offer(idx[got], tt, normal, surf)


class _Crown:
    """Semi-transparent tree crown: union of spherical lobes with a leaf free path."""

    def __init__(self, side, centres, radii, free_path, leaf):
        self.side, self.centres, self.radii = side, centres, radii
        self.free_path, self.leaf = free_path, leaf
        lo, hi = (centres - radii[:, None]).min(0), (centres + radii[:, None]).max(0)
        self.kmin, self.kmax = _krange(lo[0], hi[0], lo[1], hi[1])

    def interval(self, r: _Rays):
        t_in, t_out = np.full(r.ox.size, np.inf), np.full(r.ox.size, -np.inf)
        for c, rad in zip(self.centres, self.radii):
            a, b = _ellipsoid(r, c, (rad, rad, rad))
            t_in, t_out = np.minimum(t_in, a), np.maximum(t_out, b)
        t_in = np.maximum(t_in, 0.0)
        return np.where(t_out > t_in, t_in, np.inf), t_out


# ------------------------------------------------------------------------ materials
def _surf(cls, label, refl, rgb, part=0) -> _Surf:
    return (cls, label, float(refl), float(rgb[0]), float(rgb[1]), float(rgb[2]), part)


_ASPHALT = _surf(11, 1, 0.14, (72, 72, 75))
_MARK_WHITE = _surf(11, 2, 0.65, (225, 225, 220))
_MARK_YELLOW = _surf(11, 2, 0.55, (220, 180, 50))
_SIDEWALK = _surf(2, 1, 0.35, (178, 172, 162))
_KERB_S = _surf(2, 1, 0.40, (160, 158, 152), part=1)
_GLASS = _surf(6, 4, 0.06, (45, 55, 65), part=2)
_INTERIOR = _surf(6, 4, 0.18, (75, 65, 58), part=2)
_CAR_GLASS = _surf(1, 7, 0.05, (30, 35, 42))
_CAR_INSIDE = _surf(1, 7, 0.12, (40, 38, 36))
_TYRE = _surf(1, 7, 0.05, (28, 28, 30))
_POLE_METAL = _surf(1, 6, 0.40, (125, 125, 130))
_POLE_WOOD = _surf(1, 6, 0.30, (105, 85, 62))
_LAMP = _surf(1, 6, 0.55, (205, 205, 195))
_WIRE = _surf(14, 5, 0.25, (40, 40, 40))
_TRUNK = _surf(5, 3, 0.30, (92, 72, 52))
_RAILING = _surf(6, 4, 0.30, (55, 55, 60))
_SLAB = _surf(6, 4, 0.45, (180, 180, 175))
_FACADES = ((0.35, (148, 72, 56)), (0.30, (112, 58, 46)), (0.50, (205, 190, 160)),
            (0.45, (150, 150, 148)), (0.60, (225, 222, 214)), (0.22, (72, 74, 80)))
_PAINTS = ((230, 230, 232), (25, 25, 28), (150, 152, 158), (110, 20, 25), (30, 50, 110),
           (200, 200, 195), (70, 75, 70))
_SIGNS = ((20, 110, 60), (200, 30, 30), (30, 70, 160), (235, 235, 235))


def _tint(rng, rgb, spread=0.08):
    return tuple(float(np.clip(v * (1.0 + rng.normal(0, spread)), 0, 255)) for v in rgb)


# ---------------------------------------------------------------------------- scene
def _rng(seed: int, stream: int, index: int):
    """Independent generator for (seed, stream, index); index may be negative."""
    zigzag = 2 * index if index >= 0 else -2 * index - 1
    return np.random.default_rng(np.random.SeedSequence([seed, stream, zigzag]))


def _add_buildings(rng, x_lo, s, prims):
    side = 1 if s > 0 else 0
    pos, end = x_lo, x_lo + _TILE
    while end - pos > 0.01:
        width = rng.uniform(7.0, 22.0)
        if end - pos - width < 6.0:
            width = end - pos
        if rng.random() < 0.12:  # alley: open ground between neighbours
            pos += min(width, rng.uniform(2.5, 5.0))
            continue
        x0, x1 = pos, pos + width
        pos = x1
        yf = rng.uniform(10.0, 12.5)
        gf, fh = rng.uniform(3.6, 4.6), rng.uniform(2.9, 3.4)
        nup = int(rng.integers(1, 9))
        height = gf + nup * fh + rng.uniform(0.4, 1.2)
        refl, rgb = _FACADES[int(rng.integers(len(_FACADES)))]
        wall = _surf(6, 4, refl * rng.uniform(0.85, 1.15), _tint(rng, rgb))
        px = rng.uniform(2.4, 4.0)
        curtain = rng.random() < 0.12
        if curtain:
            ww, wh, sill, recess = px - 0.12, fh - 0.5, 0.25, 0.06
        else:
            ww, wh = rng.uniform(0.9, min(1.7, px - 0.6)), rng.uniform(1.3, 1.9)
            sill, recess = rng.uniform(0.8, 1.0), rng.uniform(0.12, 0.35)
        shop = rng.random() < 0.6
        ww0, wh0, sill0 = (px - 0.45, gf - 1.2, 0.45) if shop else (ww, wh, 1.0)
        ncol = max(0, int(np.floor((width - 1.6 - max(ww, ww0)) / px)) + 1)
        span = (ncol - 1) * px + ww
        grid = dict(ncol=ncol, px=px, x_start=x0 + (width - span) / 2, gf=gf, fh=fh, nup=nup,
                    ww=ww, wh=wh, sill=sill, ww0=ww0, wh0=wh0, sill0=sill0, recess=recess)
        prims.append(_Building(side, x0, x1, yf, 15.0, height, wall, grid))
        if rng.random() < 0.5:  # cornice
            ylo, yhi = sorted((s * (yf - 0.35), s * yf))
            prims.append(_Box(side, (x0, ylo, height - 0.55), (x1, yhi, height - 0.2), wall))
        if not curtain and ncol and rng.random() < 0.35:
            _add_balconies(rng, side, s, yf, grid, prims)


def _add_balconies(rng, side, s, yf, g, prims):
    step = int(rng.integers(1, 3))
    width = min(g["ww"] + rng.uniform(1.0, 1.8), step * g["px"] - 0.3)
    depth = rng.uniform(1.0, 1.5)
    glass_rail = rng.random() < 0.3
    rail = _surf(6, 4, 0.08, (70, 90, 95)) if glass_rail else _RAILING
    bars_x = None if glass_rail else (0, 0.12)
    bars_y = None if glass_rail else (1, 0.12)
    y_out, y_in = s * (yf - depth), s * yf
    ylo, yhi = min(y_out, y_in), max(y_out, y_in)
    rail_lo, rail_hi = sorted((y_out, y_out + s * 0.04))
    for col in range(int(rng.integers(0, step)), g["ncol"], step):
        xc = g["x_start"] + col * g["px"] + g["ww"] / 2
        x0, x1 = xc - width / 2, xc + width / 2
        for fl in range(1, g["nup"] + 1):
            z = g["gf"] + (fl - 1) * g["fh"]
            prims.append(_Box(side, (x0, ylo, z - 0.18), (x1, yhi, z), _SLAB))
            prims.append(_Box(side, (x0, rail_lo, z), (x1, rail_hi, z + 1.05), rail, bars_x))
            for xa in (x0, x1 - 0.04):
                prims.append(_Box(side, (xa, ylo, z), (xa + 0.04, yhi, z + 1.05), rail, bars_y))


def _add_cars(rng, x_lo, s, prims):
    side = 1 if s > 0 else 0
    pos, end = x_lo + rng.uniform(0.0, 4.0), x_lo + _TILE
    while True:
        length, width = rng.uniform(4.0, 5.0), rng.uniform(1.72, 1.9)
        if pos + length > end:
            return
        if rng.random() < 0.65:
            yc = s * (_ROAD_HALF - rng.uniform(0.15, 0.4) - width / 2)
            top = rng.uniform(0.85, 1.1)
            paint = _surf(1, 7, rng.uniform(0.3, 0.6),
                          _tint(rng, _PAINTS[int(rng.integers(len(_PAINTS)))], 0.05))
            prims.append(_Box(side, (pos, yc - width / 2, 0.3), (pos + length, yc + width / 2, top),
                              paint))
            prims.append(_Cabin(side, (pos + 0.47 * length, yc, top),
                                (0.33 * length, 0.47 * width, rng.uniform(0.45, 0.6)), paint))
            for xw in (pos + 0.8, pos + length - 0.8):
                for yw in (yc - width / 2 + 0.02, yc + width / 2 - 0.24):
                    prims.append(_YCyl(side, xw, 0.32, 0.32, yw, yw + 0.22, _TYRE))
            pos += length + rng.uniform(0.8, 3.0)
        else:
            pos += rng.uniform(5.0, 7.0)


def _add_furniture(rng, x_lo, s, prims, crowns, avoid):
    """Trees, street lights and sign poles along the sidewalk, clear of `avoid` (x)."""
    side = 1 if s > 0 else 0
    pos = x_lo + rng.uniform(3.0, 7.0)
    while pos < x_lo + _TILE - 4.0:
        kind = rng.random()
        if all(abs(pos - a) >= 1.5 for a in avoid):
            if kind < 0.55:
                _add_tree(rng, side, pos, s * 8.4, prims, crowns)
            elif kind < 0.8:
                _add_street_light(rng, side, s, pos, prims)
            else:
                _add_sign(rng, side, s, pos, prims)
        pos += rng.uniform(7.0, 13.0)


def _add_street_light(rng, side, s, x, prims):
    """Metal pole with an arm over the road and a lamp head."""
    y, height, arm = s * 7.45, rng.uniform(7.0, 9.0), rng.uniform(1.5, 2.5)
    ye = y - s * arm
    prims.append(_VCyl(side, x, y, 0.1, -0.3, height, _POLE_METAL))
    prims.append(_YCyl(side, x, height - 0.25, 0.05, min(y, ye), max(y, ye), _POLE_METAL))
    prims.append(_Box(side, (x - 0.15, ye - 0.3, height - 0.45),
                      (x + 0.15, ye + 0.3, height - 0.25), _LAMP))


def _add_sign(rng, side, s, x, prims):
    """Thin post with a retro-reflective plate facing the traffic."""
    y, height = s * 7.4, rng.uniform(2.8, 3.5)
    prims.append(_VCyl(side, x, y, 0.04, -0.3, height, _POLE_METAL))
    plate = _surf(1, 6, 0.95, _SIGNS[int(rng.integers(len(_SIGNS)))], part=3)
    prims.append(_Box(side, (x - 0.06, y - 0.35, height - 0.7), (x - 0.04, y + 0.35, height),
                      plate))


def _add_tree(rng, side, x, y, prims, crowns):
    radius = rng.uniform(1.8, 3.2)
    cz = rng.uniform(2.3, 3.5) + radius
    trunk_r = rng.uniform(0.12, 0.25)
    prims.append(_VCyl(side, x, y, trunk_r, -0.3, cz, _TRUNK))
    n = int(rng.integers(4, 7))
    spread = np.array([0.35, 0.35, 0.25]) * radius
    centres = np.array([x, y, cz]) + rng.normal(0, 1, (n, 3)) * spread
    radii = radius * rng.uniform(0.55, 0.8, n)
    leaf = _surf(5, 3, rng.uniform(0.35, 0.5),
                 _tint(rng, rng.uniform((55, 100, 35), (90, 140, 60)), 0.05))
    crowns.append(_Crown(side, centres, radii, rng.uniform(0.4, 0.9), leaf))


# Utility line on the left sidewalk: wooden poles mid-tile, three sagging wires.
_UTIL_Y = 7.8
_UTIL_H = 9.6
_WIRES = ((_UTIL_Y - 0.7, 0.0), (_UTIL_Y + 0.7, 0.0), (_UTIL_Y, 0.7))  # (y, dz at the pole)


def _wire_z(x):
    """Height of the wire base line at x: catenary-like sag between poles at 40 t + 20."""
    u = (np.mod(x - 0.5 * _TILE, _TILE) - 0.5 * _TILE) / (0.5 * _TILE)
    return _UTIL_H - 0.9 * (1.0 - u * u)


def _add_utility_pole(x_lo, prims):
    xp = x_lo + 0.5 * _TILE
    prims.append(_VCyl(1, xp, _UTIL_Y, 0.15, -0.3, _UTIL_H + 1.0, _POLE_WOOD))
    prims.append(_Box(1, (xp - 0.05, _UTIL_Y - 0.9, _UTIL_H - 0.12),
                      (xp + 0.05, _UTIL_Y + 0.9, _UTIL_H), _POLE_WOOD))
    return xp


@lru_cache(maxsize=64)
def _tile(seed: int, t: int):
    """Scene primitives and crowns of tile t (x in [40 t, 40 t + 40)); cached."""
    rng = _rng(seed, _TILE_STREAM, t)
    prims: list = []
    crowns: list = []
    x_lo = t * _TILE
    xp = _add_utility_pole(x_lo, prims)
    for s in (-1, 1):
        _add_buildings(rng, x_lo, s, prims)
        _add_cars(rng, x_lo, s, prims)
        _add_furniture(rng, x_lo, s, prims, crowns, (xp,) if s > 0 else ())
    return tuple(prims), tuple(crowns)


# ------------------------------------------------------------------------- scanning
def _drive_params(seed: int):
    rng = _rng(seed, _DRIVE, 0)
    return rng.uniform(0, 2 * np.pi, 4)


def _trajectory(tau, phases):
    """Scanner position at time tau (in scan lines since the start)."""
    sec = tau / _LINE_RATE
    x = _SPEED * sec + 1.5 * (np.sin(2 * np.pi * sec / 23.0 + phases[0]) - np.sin(phases[0]))
    y = _LANE_Y + 0.15 * np.sin(2 * np.pi * sec / 31.0 + phases[1])
    z = (_SENSOR_H + 0.012 * np.sin(2 * np.pi * sec / 1.7 + phases[2])
         + 0.006 * np.sin(2 * np.pi * sec / 0.45 + phases[3]))
    return x, y, z


def _ground(r: _Rays, idx, hits: _Hits, reg: _Registry) -> None:
    """Road halves with camber and markings, kerb faces, sidewalks (out to |y| = _Y_MAX)."""
    for s in (-1.0, 1.0):
        for a, b, lo, hi, surf in ((_CROWN, -_SLOPE * s, 0.0, _ROAD_HALF, None),
                                   (_EDGE_Z + _KERB - _SLOPE * _ROAD_HALF, _SLOPE * s,
                                    _ROAD_HALF, _Y_MAX, _SIDEWALK)):
            t = (a + b * r.oy - r.oz) / (r.dz - b * r.dy)
            y = r.oy + t * r.dy
            t = np.where((t > 0) & (s * y >= lo) & (s * y < hi), t, np.inf)
            if surf is None:
                x = r.ox + t * r.dx
                sid = np.full(t.size, reg(_ASPHALT), np.int32)
                dash = np.mod(x, 9.0) < 3.0
                sid[(np.abs(np.abs(y) - 3.5) < 0.06) & dash] = reg(_MARK_WHITE)
                sid[np.abs(np.abs(y) - 0.12) < 0.05] = reg(_MARK_YELLOW)
            else:
                sid = reg(surf)
            norm = np.sqrt(1.0 + b * b)
            hits.offer(idx, t, (0.0, -b / norm, 1.0 / norm), sid)
        t = (s * _ROAD_HALF - r.oy) / r.dy
        z = r.oz + t * r.dz
        t = np.where((t > 0) & (z >= _EDGE_Z) & (z <= _EDGE_Z + _KERB), t, np.inf)
        hits.offer(idx, t, (0.0, -s, 0.0), reg(_KERB_S))


def _wires(r: _Rays, idx, hits: _Hits, reg: _Registry) -> None:
    for yw, dz in _WIRES:
        zc = _wire_z(r.key - _TAN * yw) + dz
        t = _quad_in(r.oy - yw, r.oz - zc, r.dy, r.dz, 0.012)
        fin = np.where(np.isfinite(t), t, 0.0)
        normal = (0.0, (r.oy + fin * r.dy - yw) / 0.012, (r.oz + fin * r.dz - zc) / 0.012)
        hits.offer(idx, t, normal, reg(_WIRE))


_THETA = 2 * np.pi * (np.arange(_PULSES) + 0.5) / _PULSES
_SIDE_PULSES = (np.nonzero(np.cos(_THETA) < 0)[0], np.nonzero(np.cos(_THETA) > 0)[0])
# LAS convention: negative scan angles to the left; beams above horizontal saturate.
_SCAN_ANGLE = np.clip(-(np.mod(np.degrees(_THETA) - 90.0, 360.0) - 180.0), -90, 90).round()


def _scan_side(seed, side, lines, phases, reg, rng):
    """Cast one side's rays of a block; returns per-return arrays (unsorted)."""
    p = _SIDE_PULSES[side]
    ray_id = (lines[:, None] * _PULSES + p[None, :]).ravel()
    tau = ray_id / _PULSES + 0.5 / _PULSES
    ox, oy, oz = _trajectory(tau, phases)
    th = _THETA[ray_id % _PULSES]
    c, sn = np.cos(th), np.sin(th)
    r = _Rays(ox, oy, oz, -np.sin(_TILT) * c, np.cos(_TILT) * c, sn)
    n = ray_id.size
    hits = _Hits(n)
    everything = np.arange(n)
    _ground(r, everything, hits, reg)
    if side == 1:
        _wires(r, everything, hits, reg)
    k_lo, k_hi = r.key[0], r.key[-1]
    margin = _TAN * _Y_MAX + 1.0
    tiles = range(int(np.floor((k_lo - margin) / _TILE)) - 1,
                  int(np.floor((k_hi + margin) / _TILE)) + 2)
    veg_in, veg_out = np.full(n, np.inf), np.full(n, np.inf)
    veg_fp, veg_surf = np.zeros(n), np.zeros(n, np.int32)
    for t in tiles:
        prims, crowns = _tile(seed, t)
        for prim in prims:
            if prim.side != side or prim.kmax < k_lo or prim.kmin > k_hi:
                continue
            a, b = np.searchsorted(r.key, (prim.kmin, prim.kmax))
            if b > a:
                idx = everything[a:b]
                prim.cast(r.take(slice(a, b)), idx, hits, reg, rng)
        for crown in crowns:
            if crown.side != side or crown.kmax < k_lo or crown.kmin > k_hi:
                continue
            a, b = np.searchsorted(r.key, (crown.kmin, crown.kmax))
            if b > a:
                t_in, t_out = crown.interval(r.take(slice(a, b)))
                m = t_in < veg_in[a:b]
                j = np.nonzero(m)[0] + a
                veg_in[j], veg_out[j] = t_in[m], t_out[m]
                veg_fp[j], veg_surf[j] = crown.free_path, reg(crown.leaf)
    return _returns(r, ray_id, hits, veg_in, veg_out, veg_fp, veg_surf, rng)


def _returns(r, ray_id, hits, veg_in, veg_out, veg_fp, veg_surf, rng):
    """Turn nearest solid hits and crown intervals into (up to 3) returns per pulse."""
    t_solid = hits.t
    solid = (hits.surf > 0) & (t_solid >= _MIN_RANGE) & (t_solid <= _MAX_RANGE)
    v = np.nonzero(veg_in < t_solid)[0]
    depth = np.cumsum(rng.exponential(1.0, (v.size, 3)) * veg_fp[v, None], axis=1)
    depth += np.arange(3) * _VEG_SEP
    t_veg = veg_in[v, None] + depth
    limit = np.minimum(veg_out[v], t_solid[v] - _VEG_SEP)
    ok = (t_veg < limit[:, None]) & (t_veg >= _MIN_RANGE)
    n_veg = np.zeros(t_solid.size, np.int64)
    n_veg[v] = ok.sum(1)
    keep = solid & (n_veg < 3)
    keep[v] &= rng.random(v.size) < 0.75 ** n_veg[v]
    n_ret = n_veg + keep
    vi, vk = np.nonzero(ok)
    rank = np.cumsum(ok, axis=1)[vi, vk]
    s_idx = np.nonzero(keep)[0]
    rows = np.concatenate([v[vi], s_idx])
    return dict(
        t=np.concatenate([t_veg[vi, vk], t_solid[s_idx]]),
        ret=np.concatenate([rank, n_veg[s_idx] + 1]), nret=n_ret[rows],
        surf=np.concatenate([veg_surf[v[vi]], hits.surf[s_idx]]),
        cos=np.concatenate([rng.uniform(0.2, 1.0, vi.size),
                            np.abs(hits.n[0, s_idx] * r.dx[s_idx] + hits.n[1, s_idx] * r.dy[s_idx]
                                   + hits.n[2, s_idx] * r.dz[s_idx])]),
        gid=ray_id[rows], o=(r.ox[rows], r.oy[rows], r.oz[rows]),
        d=(r.dx[rows], r.dy[rows], r.dz[rows]))


def _scan_block(seed: int, j: int, phases) -> dict:
    """All returns of scan lines [j B, (j + 1) B) in time order, as LAS-ready arrays."""
    rng = _rng(seed, _BLOCK_STREAM, j)
    lines = np.arange(j * _LINES_PER_BLOCK, (j + 1) * _LINES_PER_BLOCK)
    reg = _Registry()
    sides = [_scan_side(seed, s, lines, phases, reg, rng) for s in (0, 1)]
    cat = {k: np.concatenate([sd[k] for sd in sides])
           for k in ("t", "ret", "nret", "surf", "cos", "gid")}
    o = [np.concatenate([sd["o"][a] for sd in sides]) for a in range(3)]
    d = [np.concatenate([sd["d"][a] for sd in sides]) for a in range(3)]
    order = np.argsort(cat["gid"] * 4 + cat["ret"], kind="stable")
    cat = {k: v[order] for k, v in cat.items()}
    o, d = [a[order] for a in o], [a[order] for a in d]
    n = order.size
    t = cat["t"] + rng.normal(0.0, 1.0, n) * (0.01 + 0.0004 * cat["t"])
    table = np.array(reg.rows, dtype=np.float64)
    row = table[cat["surf"]]
    energy = 0.7 ** (cat["ret"] - 1) * np.where(cat["nret"] > 1, 0.6, 1.0)
    inten = (row[:, 2] * (0.25 + 0.75 * cat["cos"]) * energy / (1.0 + (t / 45.0) ** 2)
             * 60000.0 * np.exp(rng.normal(0.0, 0.1, n)))
    shade = (0.8 + 0.2 * cat["cos"]) * np.exp(rng.normal(0.0, 0.05, n))
    rgb = row[:, 3:6] * shade[:, None] * np.exp(rng.normal(0.0, 0.03, (n, 3)))
    pulse = cat["gid"] % _PULSES
    return dict(
        X=np.round((o[0] + t * d[0]) / _SCALE).astype(np.int32),
        Y=np.round((o[1] + t * d[1]) / _SCALE).astype(np.int32),
        Z=np.round((o[2] + t * d[2]) / _SCALE).astype(np.int32),
        intensity=np.clip(inten, 1, 65535).astype(np.uint16),
        return_number=cat["ret"].astype(np.uint8),
        number_of_returns=cat["nret"].astype(np.uint8),
        classification=row[:, 0].astype(np.uint8),
        user_data=row[:, 1].astype(np.uint8),
        surface_part=row[:, 6].astype(np.uint8),
        scan_angle_rank=_SCAN_ANGLE[pulse].astype(np.int8),
        gps_time=_GPS_T0 + (cat["gid"] + 0.5) / (_PULSES * _LINE_RATE),
        rgb=(np.clip(rgb, 0, 255) * 257).astype(np.uint16),
    )


def _blocks(n_points: int, seed: int):
    """Yield scan blocks in order, trimming the last so exactly n_points are produced."""
    phases = _drive_params(seed)
    left, j = n_points, 0
    while left > 0:
        # Misses are inf distances; inf/nan arithmetic on them is expected.
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            block = _scan_block(seed, j, phases)
        size = block["X"].size
        if size > left:
            block = {k: v[:left] for k, v in block.items()}
            size = left
        left -= size
        j += 1
        yield block


# --------------------------------------------------------------------------- output
def _header() -> laspy.LasHeader:
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales = np.array([_SCALE] * 3)
    header.offsets = np.array(ORIGIN)
    header.creation_date = _CREATION_DATE
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


def _record(parts: list, header: laspy.LasHeader) -> laspy.ScaleAwarePointRecord:
    n = sum(p["X"].size for p in parts)
    rec = laspy.ScaleAwarePointRecord.zeros(n, header=header)
    for key in parts[0].keys() - {"surface_part"}:
        col = np.concatenate([p[key] for p in parts])
        if key == "rgb":
            rec.red, rec.green, rec.blue = col[:, 0], col[:, 1], col[:, 2]
        else:
            rec[key] = col
    rec.point_source_id = np.full(n, _POINT_SOURCE_ID, np.uint16)
    return rec


def surface_parts(n_points: int, seed: int = 0) -> np.ndarray:
    """(n_points,) uint8 part code (PARTS) of each point of write_street_scan(path, n_points, seed), in file
    order: the scan is regenerated, so this costs about as long as writing it."""
    return np.concatenate([block["surface_part"] for block in _blocks(n_points, seed)])


def write_street_scan(path: str | os.PathLike, n_points: int = 1_500_000, seed: int = 0,
                      chunk_points: int = 500_000) -> int:
    """Write a simulated mobile-LiDAR street scan of about n_points points to a LAS/LAZ file (by suffix); return the exact count written.

    The count is exactly n_points; the street grows with n_points (about 7.5 k points
    per metre).  Same (n_points, seed) gives a byte-identical file for any chunk_points,
    which only bounds how many points are held in memory before each write.  The file
    is written under a temporary name in the same folder and renamed when complete.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".las", ".laz"):
        raise ValueError(f"path must end in .las or .laz, got {path.name!r}")
    if n_points < 1 or chunk_points < 1 or seed < 0:
        raise ValueError("n_points and chunk_points must be >= 1 and seed >= 0")
    header = _header()
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex}.tmp")
    written = 0
    try:
        with laspy.open(tmp, mode="w", header=header, do_compress=suffix == ".laz") as writer:
            pending: list = []
            held = 0
            for block in _blocks(n_points, seed):
                pending.append(block)
                held += block["X"].size
                if held >= chunk_points:
                    writer.write_points(_record(pending, header))
                    written += held
                    pending, held = [], 0
            if pending:
                writer.write_points(_record(pending, header))
                written += held
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return written
