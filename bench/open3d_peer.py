"""Open3D's voxel_down_sample and farthest_point_down_sample on LAS/LAZ points, timed in this process.

Run as a child of bench/throughput.py so its peak memory is measured alone. Prints one JSON line, with the
seconds spent searching the voxel size (30 calls: the parent takes them off the wall time, as the
CloudCompare peer's distance search is untimed).
"""
from __future__ import annotations

import json
import sys
import time

import laspy
import numpy as np
import open3d as o3d


def load_points(paths: list[str]) -> np.ndarray:
    """All points of the files, centred (as the pipeline does per tile) to keep float precision."""
    xyz = np.concatenate([np.column_stack([las.x, las.y, las.z]) for las in map(laspy.read, paths)])
    return xyz - xyz.mean(axis=0)


def voxel_size_for(cloud: o3d.geometry.PointCloud, target: int) -> float:
    """Voxel edge giving about `target` points (bisection on the log of the size; untimed)."""
    low, high = 1e-3, 100.0
    for _ in range(30):
        mid = (low * high) ** 0.5
        if len(cloud.voxel_down_sample(mid).points) > target:
            low = mid
        else:
            high = mid
    return high


def main(operation: str, ratio: float, paths: list[str]) -> None:
    xyz = load_points(paths)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
    target = int(round(ratio * len(xyz)))
    started = time.perf_counter()
    if operation == "voxel":
        size = voxel_size_for(cloud, target)
        search, started = time.perf_counter() - started, time.perf_counter()
        kept = len(cloud.voxel_down_sample(size).points)
    else:
        search = 0.0
        kept = len(cloud.farthest_point_down_sample(target).points)
    seconds = time.perf_counter() - started
    print(json.dumps({"points": len(xyz), "kept": kept, "seconds": seconds, "search_seconds": search}))


if __name__ == "__main__":
    main(sys.argv[1], float(sys.argv[2]), sys.argv[3:])
