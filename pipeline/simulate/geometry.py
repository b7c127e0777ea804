"""Rays and what they hit: bundles of rays sorted by key, the nearest hit per ray, and the analytic primitives
of the scene (boxes, building blocks with recessed windows, cylinders, car cabins, tree crowns)."""
from __future__ import annotations

import numpy as np

from pipeline.simulate.street import (CAR_GLASS, CAR_INSIDE, GLASS, INSIDE_SHARE, INTERIOR, PANE_SHARE, TAN_TILT,
                                      Material)

Point = tuple[float, float, float]  # x, y, z of a corner, a centre or semi-axes
Normal = tuple[np.ndarray | float, np.ndarray | float, np.ndarray | float]  # per-axis components or constants


class RayBundle:
    """Rays of one scanner side in one block, sorted by key = x + tan(tilt) * y."""

    __slots__ = ("ox", "oy", "oz", "dx", "dy", "dz", "key")

    def __init__(self, ox: np.ndarray, oy: np.ndarray, oz: np.ndarray, dx: np.ndarray, dy: np.ndarray,
                 dz: np.ndarray) -> None:
        self.ox, self.oy, self.oz, self.dx, self.dy, self.dz = ox, oy, oz, dx, dy, dz
        self.key = ox + TAN_TILT * oy

    def take(self, sel: slice | np.ndarray) -> RayBundle:
        """The rays selected by a slice, mask or index array."""
        return RayBundle(self.ox[sel], self.oy[sel], self.oz[sel],
                     self.dx[sel], self.dy[sel], self.dz[sel])


class NearestHits:
    """Nearest solid hit per ray: distance, normal and surface id (0 = no return)."""

    def __init__(self, n: int) -> None:
        self.t = np.full(n, np.inf)
        self.n = np.zeros((3, n))
        self.surf = np.zeros(n, np.int32)

    def offer(self, idx: np.ndarray, t: np.ndarray, normal: Normal, surf: int | np.ndarray) -> None:
        """Keep (t, normal, surf) for rays idx where t is nearer than the current hit."""
        m = t < self.t[idx]
        if not m.any():
            return
        j = idx[m]
        self.t[j] = t[m]
        for a in range(3):
            self.n[a, j] = np.broadcast_to(normal[a], t.shape)[m]
        self.surf[j] = np.broadcast_to(surf, t.shape)[m]


class SurfaceTable:
    """Maps surface descriptors to small ids for one block (id 0 = no return)."""

    def __init__(self) -> None:
        self.ids: dict = {None: 0}
        self.rows: list = [(0, 0, 0.0, 0.0, 0.0, 0.0, 0)]

    def __call__(self, surf: Material | None) -> int:
        """The id of `surf` in this block, given on first sight."""
        if surf not in self.ids:
            self.ids[surf] = len(self.rows)
            self.rows.append(surf)
        return self.ids[surf]


def key_range(xlo: float, xhi: float, ylo: float, yhi: float) -> tuple[float, float]:
    """Range of ray keys that can reach the box [xlo, xhi] x [ylo, yhi]."""
    return xlo + TAN_TILT * ylo - 0.05, xhi + TAN_TILT * yhi + 0.05


def box_entry(r: RayBundle, lo: Point, hi: Point) -> tuple[np.ndarray, np.ndarray]:
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


def face_normal(r: RayBundle, axis: np.ndarray) -> Normal:
    """Outward normal of the box face crossed along `axis` (facing the ray)."""
    return tuple(np.where(axis == a, -np.sign(d), 0.0) for a, d in enumerate((r.dx, r.dy, r.dz)))


def circle_entry(px: np.ndarray, py: np.ndarray, ux: np.ndarray, uy: np.ndarray, rad: float) -> np.ndarray:
    """Nearest positive root of |p + t u| = rad in 2-D (inf = miss)."""
    a = ux * ux + uy * uy
    b = px * ux + py * uy
    disc = b * b - a * (px * px + py * py - rad * rad)
    t = (-b - np.sqrt(np.maximum(disc, 0.0))) / a
    return np.where((disc > 0) & (t > 0), t, np.inf)


def ellipsoid_span(r: RayBundle, c: Point, s: Point) -> tuple[np.ndarray, np.ndarray]:
    """Entry and exit distances of rays through an ellipsoid (centre c, semi-axes s)."""
    p = [(o - ci) / si for o, ci, si in zip((r.ox, r.oy, r.oz), c, s)]
    u = [d / si for d, si in zip((r.dx, r.dy, r.dz), s)]
    a = u[0] ** 2 + u[1] ** 2 + u[2] ** 2
    b = p[0] * u[0] + p[1] * u[1] + p[2] * u[2]
    disc = b * b - a * (p[0] ** 2 + p[1] ** 2 + p[2] ** 2 - 1.0)
    root = np.sqrt(np.maximum(disc, 0.0))
    ok = disc > 0
    return np.where(ok, (-b - root) / a, np.inf), np.where(ok, (-b + root) / a, -np.inf)


def through_glass(t: np.ndarray, extra: np.ndarray, rng: np.random.Generator, glass: Material, inner: Material,
                  reg: SurfaceTable) -> tuple[np.ndarray, np.ndarray]:
    """Split pulses reaching glass at t into pane returns, returns from `extra` behind it,
    and lost pulses (no return, but nothing behind is seen either)."""
    u = rng.random(t.size)
    t = t.copy()
    surf = np.full(t.size, reg(glass), np.int32)
    behind = (u >= PANE_SHARE) & (u < PANE_SHARE + INSIDE_SHARE)
    t[behind] += extra[behind]
    surf[behind] = reg(inner)
    surf[u >= PANE_SHARE + INSIDE_SHARE] = 0
    return t, surf


class Primitive:
    """A solid scene element on one side of the street (0 = right/-y, 1 = left/+y)."""

    side: int
    kmin: float
    kmax: float

    def cast(self, r: RayBundle, idx: np.ndarray, hits: NearestHits, reg: SurfaceTable,
             rng: np.random.Generator) -> None:
        """Offer `hits` this element's nearest hit for the rays `r` (rows `idx` of the bundle)."""
        raise NotImplementedError


class Box(Primitive):
    """Axis-aligned solid box; `bars` makes it a railing (top rail + balusters along an axis)."""

    def __init__(self, side: int, lo: Point, hi: Point, surf: Material, bars: tuple[int, float] | None = None) -> None:
        self.side, self.lo, self.hi, self.surf, self.bars = side, lo, hi, surf, bars
        self.kmin, self.kmax = key_range(lo[0], hi[0], lo[1], hi[1])

    def cast(self, r: RayBundle, idx: np.ndarray, hits: NearestHits, reg: SurfaceTable,
             rng: np.random.Generator) -> None:
        t, axis = box_entry(r, self.lo, self.hi)
        if self.bars is not None:  # gaps between balusters below the top rail
            bar_axis, pitch = self.bars
            along = (r.ox, r.oy)[bar_axis] + t * (r.dx, r.dy)[bar_axis]
            z = r.oz + t * r.dz
            solid = (np.mod(along, pitch) < 0.03) | (z > self.hi[2] - 0.05)
            t = np.where(solid, t, np.inf)
        hits.offer(idx, t, face_normal(r, axis), reg(self.surf))


class BuildingBlock(Primitive):
    """Building block whose street facade has a grid of recessed glazed openings."""

    def __init__(self, side: int, x0: float, x1: float, yf: float, depth: float, height: float, wall: Material,
                 grid: dict[str, float]) -> None:
        s = 1 if side else -1
        self.side, self.s, self.yf, self.wall = side, s, s * yf, wall
        y_lo, y_hi = sorted((s * yf, s * (yf + depth)))
        self.lo, self.hi = (x0, y_lo, -0.5), (x1, y_hi, height)
        self.kmin, self.kmax = key_range(x0, x1, y_lo, y_hi)
        self.g = grid
        self.reveal = wall[:3] + tuple(0.85 * v for v in wall[3:])

    def cast(self, r: RayBundle, idx: np.ndarray, hits: NearestHits, reg: SurfaceTable,
             rng: np.random.Generator) -> None:
        t, axis = box_entry(r, self.lo, self.hi)
        got = np.nonzero(np.isfinite(t))[0]
        if got.size == 0:
            return
        rg, t, axis = r.take(got), t[got], axis[got]
        normal = face_normal(rg, axis)
        surf = np.full(got.size, reg(self.wall), np.int32)
        if self.g["ncol"]:
            self._openings(rg, t, normal, surf, axis == 1, reg, rng)
        hits.offer(idx[got], t, normal, surf)

    def _openings(self, r: RayBundle, t: np.ndarray, normal: Normal, surf: np.ndarray, facade: np.ndarray,
                  reg: SurfaceTable, rng: np.random.Generator) -> None:
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
        t[w[pane]], surf[w[pane]] = through_glass(tp, extra, rng, GLASS, INTERIOR, reg)


class Cylinder(Primitive):
    """A cylinder along the z axis (pole, trunk: `along` 2, `centre` its x, y) or the y axis (lamp arm,
    wheel: `along` 1, `centre` its x, z), from `lo` to `hi` along it."""

    def __init__(self, side: int, along: int, centre: tuple[float, float], rad: float, lo: float, hi: float,
                 surf: Material) -> None:
        self.side, self.along, self.c, self.rad, self.span, self.surf = side, along, centre, rad, (lo, hi), surf
        self.cross = (0, 1) if along == 2 else (0, 2)  # the axes of its circle
        ylo, yhi = (centre[1] - rad, centre[1] + rad) if along == 2 else (lo, hi)
        self.kmin, self.kmax = key_range(centre[0] - rad, centre[0] + rad, ylo, yhi)

    def cast(self, r: RayBundle, idx: np.ndarray, hits: NearestHits, reg: SurfaceTable,
             rng: np.random.Generator) -> None:
        origin, direction = (r.ox, r.oy, r.oz), (r.dx, r.dy, r.dz)
        a, b = self.cross
        pa, pb = origin[a] - self.c[0], origin[b] - self.c[1]
        t = circle_entry(pa, pb, direction[a], direction[b], self.rad)
        s = origin[self.along] + t * direction[self.along]
        t = np.where((s >= self.span[0]) & (s <= self.span[1]), t, np.inf)
        fin = np.where(np.isfinite(t), t, 0.0)
        normal: list[np.ndarray | float] = [0.0, 0.0, 0.0]
        normal[a], normal[b] = (pa + fin * direction[a]) / self.rad, (pb + fin * direction[b]) / self.rad
        hits.offer(idx, t, (normal[0], normal[1], normal[2]), reg(self.surf))


class CarCabin(Primitive):
    """Rounded car top: upper half of an ellipsoid, glazed above the belt line."""

    def __init__(self, side: int, c: Point, s: Point, paint: Material) -> None:
        self.side, self.c, self.s, self.paint = side, c, s, paint
        self.kmin, self.kmax = key_range(c[0] - s[0], c[0] + s[0], c[1] - s[1], c[1] + s[1])

    def cast(self, r: RayBundle, idx: np.ndarray, hits: NearestHits, reg: SurfaceTable,
             rng: np.random.Generator) -> None:
        t, _ = ellipsoid_span(r, self.c, self.s)
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
        tg, sg = through_glass(tg, extra, rng, CAR_GLASS, CAR_INSIDE, reg)
        tt = t[got].copy()
        tt[glazed], surf[glazed] = tg, sg
        hits.offer(idx[got], tt, normal, surf)


class TreeCrown:
    """Semi-transparent tree crown: union of spherical lobes with a leaf free path."""

    def __init__(self, side: int, centres: np.ndarray, radii: np.ndarray, free_path: float, leaf: Material) -> None:
        self.side, self.centres, self.radii = side, centres, radii
        self.free_path, self.leaf = free_path, leaf
        lo, hi = (centres - radii[:, None]).min(0), (centres + radii[:, None]).max(0)
        self.kmin, self.kmax = key_range(lo[0], hi[0], lo[1], hi[1])

    def interval(self, r: RayBundle) -> tuple[np.ndarray, np.ndarray]:
        """Entry and exit distances of the rays through the crown's lobes (entry inf: a miss)."""
        t_in, t_out = np.full(r.ox.size, np.inf), np.full(r.ox.size, -np.inf)
        for c, rad in zip(self.centres, self.radii):
            a, b = ellipsoid_span(r, c, (rad, rad, rad))
            t_in, t_out = np.minimum(t_in, a), np.maximum(t_out, b)
        t_in = np.maximum(t_in, 0.0)
        return np.where(t_out > t_in, t_in, np.inf), t_out
