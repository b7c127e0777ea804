"""The drive and the scan: the platform's trajectory (a car in the street, or an aircraft over it), each scan
line's pulses cast against the ground, the wires and the scene, and their returns (up to three through tree
crowns) as LAS-ready arrays, block by block."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Iterator

import numpy as np

from pipeline.simulate.geometry import NearestHits, RayBundle, SurfaceTable, circle_entry
from pipeline.simulate.scene import scene_tile
from pipeline.simulate.street import (AIR_SECTOR, AIR_SPEED, ALTITUDE, ASPHALT, BLOCK_STREAM, CROWN, DRIVE_STREAM,
                                      EDGE_Z, GPS_T0, KERB, KERB_FACE, LANE_Y, LINE_RATE, LINES_PER_BLOCK, MARK_WHITE,
                                      MARK_YELLOW, MAX_RANGE, MIN_RANGE, PULSES, ROAD_HALF, SCALE, SENSOR_H, SIDEWALK,
                                      SLOPE, SPEED, TAN_TILT, TILE_LENGTH, TILT, VEG_SEP, WIRE, WIRES, Y_MAX,
                                      stream_rng, wire_height)

Block = dict[str, np.ndarray]  # a block's returns: LAS dimension name -> (n,) values (rgb: (n, 3))


def drive_phases(seed: int) -> np.ndarray:
    """(4,) phases of the drive's sway and bounce, from the seed."""
    rng = stream_rng(seed, DRIVE_STREAM, 0)
    return rng.uniform(0, 2 * np.pi, 4)


def trajectory(tau: np.ndarray, phases: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The car's scanner position at time tau (in scan lines since the start)."""
    sec = tau / LINE_RATE
    x = SPEED * sec + 1.5 * (np.sin(2 * np.pi * sec / 23.0 + phases[0]) - np.sin(phases[0]))
    y = LANE_Y + 0.15 * np.sin(2 * np.pi * sec / 31.0 + phases[1])
    z = (SENSOR_H + 0.012 * np.sin(2 * np.pi * sec / 1.7 + phases[2])
         + 0.006 * np.sin(2 * np.pi * sec / 0.45 + phases[3]))
    return x, y, z


def flight(tau: np.ndarray, phases: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The aircraft's scanner position at time tau (in scan lines since the start): along the street's centreline
    at ALTITUDE, drifting a metre across and bobbing half a metre in the air."""
    sec = tau / LINE_RATE
    x = AIR_SPEED * sec + 2.0 * (np.sin(2 * np.pi * sec / 17.0 + phases[0]) - np.sin(phases[0]))
    y = 1.0 * np.sin(2 * np.pi * sec / 29.0 + phases[1])
    z = ALTITUDE + 0.5 * np.sin(2 * np.pi * sec / 7.0 + phases[2]) + 0.1 * np.sin(2 * np.pi * sec / 1.3 + phases[3])
    return x, y, z


def cast_ground(r: RayBundle, idx: np.ndarray, hits: NearestHits, reg: SurfaceTable) -> None:
    """Road halves with camber and markings, kerb faces, sidewalks (out to |y| = Y_MAX)."""
    for s in (-1.0, 1.0):
        for a, b, lo, hi, surf in ((CROWN, -SLOPE * s, 0.0, ROAD_HALF, None),
                                   (EDGE_Z + KERB - SLOPE * ROAD_HALF, SLOPE * s,
                                    ROAD_HALF, Y_MAX, SIDEWALK)):
            t = (a + b * r.oy - r.oz) / (r.dz - b * r.dy)
            y = r.oy + t * r.dy
            t = np.where((t > 0) & (s * y >= lo) & (s * y < hi), t, np.inf)
            if surf is None:
                x = r.ox + t * r.dx
                sid = np.full(t.size, reg(ASPHALT), np.int32)
                dash = np.mod(x, 9.0) < 3.0
                sid[(np.abs(np.abs(y) - 3.5) < 0.06) & dash] = reg(MARK_WHITE)
                sid[np.abs(np.abs(y) - 0.12) < 0.05] = reg(MARK_YELLOW)
            else:
                sid = reg(surf)
            norm = np.sqrt(1.0 + b * b)
            hits.offer(idx, t, (0.0, -b / norm, 1.0 / norm), sid)
        t = (s * ROAD_HALF - r.oy) / r.dy
        z = r.oz + t * r.dz
        t = np.where((t > 0) & (z >= EDGE_Z) & (z <= EDGE_Z + KERB), t, np.inf)
        hits.offer(idx, t, (0.0, -s, 0.0), reg(KERB_FACE))


def cast_wires(r: RayBundle, idx: np.ndarray, hits: NearestHits, reg: SurfaceTable) -> None:
    """The utility line's three wires, thin horizontal cylinders sagging between poles."""
    for yw, dz in WIRES:
        zc = wire_height(r.key - TAN_TILT * yw) + dz
        t = circle_entry(r.oy - yw, r.oz - zc, r.dy, r.dz, 0.012)
        fin = np.where(np.isfinite(t), t, 0.0)
        normal = (0.0, (r.oy + fin * r.dy - yw) / 0.012, (r.oz + fin * r.dz - zc) / 0.012)
        hits.offer(idx, t, normal, reg(WIRE))


THETA = 2 * np.pi * (np.arange(PULSES) + 0.5) / PULSES
# LAS convention: negative scan angles to the left; beams above horizontal saturate.
SCAN_ANGLE = np.clip(-(np.mod(np.degrees(THETA) - 90.0, 360.0) - 180.0), -90, 90).round()
DOWNWARD = np.sin(THETA) < -np.cos(np.radians(AIR_SECTOR))  # within AIR_SECTOR of the nadir


@dataclass(frozen=True)
class Platform:
    """What carries the scanner: its position over time (tau, phases) -> x, y, z, and the pulses of a mirror
    turn it fires to each side (left, right: indices into THETA)."""

    trajectory: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]
    side_pulses: tuple[np.ndarray, np.ndarray]


PLATFORMS = {
    # a car in the right lane, its profiler turning all the way round (Toronto3D-like)
    "mobile": Platform(trajectory, (np.nonzero(np.cos(THETA) < 0)[0], np.nonzero(np.cos(THETA) > 0)[0])),
    # an aircraft over the centreline, the same tilted profiler firing only within AIR_SECTOR of the nadir
    "airborne": Platform(flight, (np.nonzero(DOWNWARD & (np.cos(THETA) < 0))[0],
                                  np.nonzero(DOWNWARD & (np.cos(THETA) > 0))[0])),
}


def scan_side(seed: int, side: int, lines: np.ndarray, phases: np.ndarray, reg: SurfaceTable,
              rng: np.random.Generator, platform: Platform) -> dict[str, Any]:
    """Cast one side's rays of a block; returns per-return arrays (unsorted)."""
    p = platform.side_pulses[side]
    ray_id = (lines[:, None] * PULSES + p[None, :]).ravel()
    tau = ray_id / PULSES + 0.5 / PULSES
    ox, oy, oz = platform.trajectory(tau, phases)
    th = THETA[ray_id % PULSES]
    c, sn = np.cos(th), np.sin(th)
    r = RayBundle(ox, oy, oz, -np.sin(TILT) * c, np.cos(TILT) * c, sn)
    n = ray_id.size
    hits = NearestHits(n)
    everything = np.arange(n)
    cast_ground(r, everything, hits, reg)
    if side == 1:
        cast_wires(r, everything, hits, reg)
    k_lo, k_hi = r.key[0], r.key[-1]
    margin = TAN_TILT * Y_MAX + 1.0
    tiles = range(int(np.floor((k_lo - margin) / TILE_LENGTH)) - 1,
                  int(np.floor((k_hi + margin) / TILE_LENGTH)) + 2)
    veg_in, veg_out = np.full(n, np.inf), np.full(n, np.inf)
    veg_fp, veg_surf = np.zeros(n), np.zeros(n, np.int32)
    for t in tiles:
        prims, crowns = scene_tile(seed, t)
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
    return pulse_returns(r, ray_id, hits, veg_in, veg_out, veg_fp, veg_surf, rng)


def pulse_returns(r: RayBundle, ray_id: np.ndarray, hits: NearestHits, veg_in: np.ndarray, veg_out: np.ndarray,
                  veg_fp: np.ndarray, veg_surf: np.ndarray, rng: np.random.Generator) -> dict[str, Any]:
    """Turn nearest solid hits and crown intervals into (up to 3) returns per pulse."""
    t_solid = hits.t
    solid = (hits.surf > 0) & (t_solid >= MIN_RANGE) & (t_solid <= MAX_RANGE)
    v = np.nonzero(veg_in < t_solid)[0]
    depth = np.cumsum(rng.exponential(1.0, (v.size, 3)) * veg_fp[v, None], axis=1)
    depth += np.arange(3) * VEG_SEP
    t_veg = veg_in[v, None] + depth
    limit = np.minimum(veg_out[v], t_solid[v] - VEG_SEP)
    ok = (t_veg < limit[:, None]) & (t_veg >= MIN_RANGE)
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


def scan_block(seed: int, j: int, phases: np.ndarray, platform: Platform) -> Block:
    """All returns of scan lines [j B, (j + 1) B) in time order, as LAS-ready arrays."""
    rng = stream_rng(seed, BLOCK_STREAM, j)
    lines = np.arange(j * LINES_PER_BLOCK, (j + 1) * LINES_PER_BLOCK)
    reg = SurfaceTable()
    sides = [scan_side(seed, s, lines, phases, reg, rng, platform) for s in (0, 1)]
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
    pulse = cat["gid"] % PULSES
    return dict(
        X=np.round((o[0] + t * d[0]) / SCALE).astype(np.int32),
        Y=np.round((o[1] + t * d[1]) / SCALE).astype(np.int32),
        Z=np.round((o[2] + t * d[2]) / SCALE).astype(np.int32),
        intensity=np.clip(inten, 1, 65535).astype(np.uint16),
        return_number=cat["ret"].astype(np.uint8),
        number_of_returns=cat["nret"].astype(np.uint8),
        classification=row[:, 0].astype(np.uint8),
        user_data=row[:, 1].astype(np.uint8),
        surface_part=row[:, 6].astype(np.uint8),
        scan_angle_rank=SCAN_ANGLE[pulse].astype(np.int8),
        gps_time=GPS_T0 + (cat["gid"] + 0.5) / (PULSES * LINE_RATE),
        rgb=(np.clip(rgb, 0, 255) * 257).astype(np.uint16),
    )


def scan_blocks(n_points: int, seed: int, platform: str = "mobile") -> Iterator[Block]:
    """Yield scan blocks in order, trimming the last so exactly n_points are produced (`platform`: a key of
    PLATFORMS)."""
    carrier = PLATFORMS[platform]
    phases = drive_phases(seed)
    left, j = n_points, 0
    while left > 0:
        # Misses are inf distances; inf/nan arithmetic on them is expected.
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            block = scan_block(seed, j, phases, carrier)
        size = block["X"].size
        if size > left:
            block = {k: v[:left] for k, v in block.items()}
            size = left
        left -= size
        j += 1
        yield block
