"""Deterministic LiDAR street-scan simulator (mobile, or airborne over the same street), streamed to LAS/LAZ.

Modules, in the order a scan is made: street (the fixed layout and materials), geometry (rays and the
scene's primitives), scene (what stands along the street, per 40 m tile), raycast (the drive, the pulses
and their returns), writing (the LAS file and each point's surface part).

Why: the simplification pipeline needs realistic, reproducible test and benchmark
clouds of any size (10 k .. 30 M points) without shipping survey data.

How: a vehicle drives along the centreline of a Toronto3D-like street (road with
camber and markings, kerbs, sidewalks, facades with recessed windows and balconies,
street lights, sign poles, a utility line, parked cars, trees).  A rotating 2-D
profiler, tilted about the vertical axis, fires pulses that are ray-cast against
analytic primitives (planes, boxes, cylinders, spheres, ellipsoids), so density
falls off with range, scan lines show as stripes and occlusion is physical.
Tree crowns are semi-transparent and give up to three returns per pulse. The airborne platform flies the
same profiler 80 m above the centreline, firing within 25 degrees of the nadir: roofs, crowns, car tops and
the road dense, facades and poles grazed, wires a few returns per span (raycast.PLATFORMS).

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
from pipeline.simulate.street import EPSG, LABELS, ORIGIN, PARTS
from pipeline.simulate.writing import surface_parts, write_street_scan

__all__ = ["EPSG", "LABELS", "ORIGIN", "PARTS", "surface_parts", "write_street_scan"]
