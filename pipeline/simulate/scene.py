"""What stands along the street, 40 m at a time: buildings with balconies and cornices, parked cars, trees,
street lights, signs and the utility poles. A tile depends only on (seed, tile index)."""
from __future__ import annotations

from functools import lru_cache

import numpy as np

from pipeline.simulate.geometry import Box, BuildingBlock, CarCabin, Cylinder, Primitive, TreeCrown
from pipeline.simulate.street import (FACADES, LAMP, PAINTS, POLE_METAL, POLE_WOOD, RAILING, ROAD_HALF, SIGNS, SLAB,
                                      TILE_LENGTH, TILE_STREAM, TRUNK, TYRE, UTIL_H, UTIL_Y, material, stream_rng, tint)


def add_buildings(rng: np.random.Generator, x_lo: float, s: int, prims: list[Primitive]) -> None:
    """A row of building blocks (with alleys, cornices and balconies) on side `s` (-1 right, 1 left) of a tile."""
    side = 1 if s > 0 else 0
    pos, end = x_lo, x_lo + TILE_LENGTH
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
        refl, rgb = FACADES[int(rng.integers(len(FACADES)))]
        wall = material(6, 4, refl * rng.uniform(0.85, 1.15), tint(rng, rgb))
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
        prims.append(BuildingBlock(side, x0, x1, yf, 15.0, height, wall, grid))
        if rng.random() < 0.5:  # cornice
            ylo, yhi = sorted((s * (yf - 0.35), s * yf))
            prims.append(Box(side, (x0, ylo, height - 0.55), (x1, yhi, height - 0.2), wall))
        if not curtain and ncol and rng.random() < 0.35:
            add_balconies(rng, side, s, yf, grid, prims)


def add_balconies(rng: np.random.Generator, side: int, s: int, yf: float, g: dict[str, float],
                  prims: list[Primitive]) -> None:
    """Slabs and railings in front of every `step`-th window column of a facade at |y| = yf."""
    step = int(rng.integers(1, 3))
    width = min(g["ww"] + rng.uniform(1.0, 1.8), step * g["px"] - 0.3)
    depth = rng.uniform(1.0, 1.5)
    glass_rail = rng.random() < 0.3
    rail = material(6, 4, 0.08, (70, 90, 95)) if glass_rail else RAILING
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
            prims.append(Box(side, (x0, ylo, z - 0.18), (x1, yhi, z), SLAB))
            prims.append(Box(side, (x0, rail_lo, z), (x1, rail_hi, z + 1.05), rail, bars_x))
            for xa in (x0, x1 - 0.04):
                prims.append(Box(side, (xa, ylo, z), (xa + 0.04, yhi, z + 1.05), rail, bars_y))


def add_cars(rng: np.random.Generator, x_lo: float, s: int, prims: list[Primitive]) -> None:
    """Cars parked along the kerb of side `s`, body, cabin and wheels, with gaps between them."""
    side = 1 if s > 0 else 0
    pos, end = x_lo + rng.uniform(0.0, 4.0), x_lo + TILE_LENGTH
    while True:
        length, width = rng.uniform(4.0, 5.0), rng.uniform(1.72, 1.9)
        if pos + length > end:
            return
        if rng.random() < 0.65:
            yc = s * (ROAD_HALF - rng.uniform(0.15, 0.4) - width / 2)
            top = rng.uniform(0.85, 1.1)
            paint = material(1, 7, rng.uniform(0.3, 0.6),
                          tint(rng, PAINTS[int(rng.integers(len(PAINTS)))], 0.05))
            prims.append(Box(side, (pos, yc - width / 2, 0.3), (pos + length, yc + width / 2, top),
                              paint))
            prims.append(CarCabin(side, (pos + 0.47 * length, yc, top),
                                (0.33 * length, 0.47 * width, rng.uniform(0.45, 0.6)), paint))
            for xw in (pos + 0.8, pos + length - 0.8):
                for yw in (yc - width / 2 + 0.02, yc + width / 2 - 0.24):
                    prims.append(Cylinder(side, 1, (xw, 0.32), 0.32, yw, yw + 0.22, TYRE))
            pos += length + rng.uniform(0.8, 3.0)
        else:
            pos += rng.uniform(5.0, 7.0)


def add_furniture(rng: np.random.Generator, x_lo: float, s: int, prims: list[Primitive], crowns: list[TreeCrown],
                  avoid: tuple[float, ...]) -> None:
    """Trees, street lights and sign poles along the sidewalk, clear of `avoid` (x)."""
    side = 1 if s > 0 else 0
    pos = x_lo + rng.uniform(3.0, 7.0)
    while pos < x_lo + TILE_LENGTH - 4.0:
        kind = rng.random()
        if all(abs(pos - a) >= 1.5 for a in avoid):
            if kind < 0.55:
                add_tree(rng, side, pos, s * 8.4, prims, crowns)
            elif kind < 0.8:
                add_street_light(rng, side, s, pos, prims)
            else:
                add_sign(rng, side, s, pos, prims)
        pos += rng.uniform(7.0, 13.0)


def add_street_light(rng: np.random.Generator, side: int, s: int, x: float, prims: list[Primitive]) -> None:
    """Metal pole with an arm over the road and a lamp head."""
    y, height, arm = s * 7.45, rng.uniform(7.0, 9.0), rng.uniform(1.5, 2.5)
    ye = y - s * arm
    prims.append(Cylinder(side, 2, (x, y), 0.1, -0.3, height, POLE_METAL))
    prims.append(Cylinder(side, 1, (x, height - 0.25), 0.05, min(y, ye), max(y, ye), POLE_METAL))
    prims.append(Box(side, (x - 0.15, ye - 0.3, height - 0.45),
                      (x + 0.15, ye + 0.3, height - 0.25), LAMP))


def add_sign(rng: np.random.Generator, side: int, s: int, x: float, prims: list[Primitive]) -> None:
    """Thin post with a retro-reflective plate facing the traffic."""
    y, height = s * 7.4, rng.uniform(2.8, 3.5)
    prims.append(Cylinder(side, 2, (x, y), 0.04, -0.3, height, POLE_METAL))
    plate = material(1, 6, 0.95, SIGNS[int(rng.integers(len(SIGNS)))], part=3)
    prims.append(Box(side, (x - 0.06, y - 0.35, height - 0.7), (x - 0.04, y + 0.35, height),
                      plate))


def add_tree(rng: np.random.Generator, side: int, x: float, y: float, prims: list[Primitive],
             crowns: list[TreeCrown]) -> None:
    """A trunk and a crown of 4-6 spherical lobes."""
    radius = rng.uniform(1.8, 3.2)
    cz = rng.uniform(2.3, 3.5) + radius
    trunk_r = rng.uniform(0.12, 0.25)
    prims.append(Cylinder(side, 2, (x, y), trunk_r, -0.3, cz, TRUNK))
    n = int(rng.integers(4, 7))
    spread = np.array([0.35, 0.35, 0.25]) * radius
    centres = np.array([x, y, cz]) + rng.normal(0, 1, (n, 3)) * spread
    radii = radius * rng.uniform(0.55, 0.8, n)
    leaf = material(5, 3, rng.uniform(0.35, 0.5),
                 tint(rng, rng.uniform((55, 100, 35), (90, 140, 60)), 0.05))
    crowns.append(TreeCrown(side, centres, radii, rng.uniform(0.4, 0.9), leaf))


def add_utility_pole(x_lo: float, prims: list[Primitive]) -> float:
    """The wooden pole and cross-arm of the utility line in the middle of the tile; its x."""
    xp = x_lo + 0.5 * TILE_LENGTH
    prims.append(Cylinder(1, 2, (xp, UTIL_Y), 0.15, -0.3, UTIL_H + 1.0, POLE_WOOD))
    prims.append(Box(1, (xp - 0.05, UTIL_Y - 0.9, UTIL_H - 0.12),
                      (xp + 0.05, UTIL_Y + 0.9, UTIL_H), POLE_WOOD))
    return xp


@lru_cache(maxsize=64)
def scene_tile(seed: int, t: int) -> tuple[tuple[Primitive, ...], tuple[TreeCrown, ...]]:
    """Scene primitives and crowns of tile t (x in [40 t, 40 t + 40)); cached."""
    rng = stream_rng(seed, TILE_STREAM, t)
    prims: list = []
    crowns: list = []
    x_lo = t * TILE_LENGTH
    xp = add_utility_pole(x_lo, prims)
    for s in (-1, 1):
        add_buildings(rng, x_lo, s, prims)
        add_cars(rng, x_lo, s, prims)
        add_furniture(rng, x_lo, s, prims, crowns, (xp,) if s > 0 else ())
    return tuple(prims), tuple(crowns)
