"""`pipeline run MESH --mesh`: simplify a triangle mesh's vertices, then re-triangulate them by ball pivoting.

The paper's mesh extension (section 5): vertices are simplified as a point cloud (the learned GNN over
the mesh adjacency instead of a kNN graph), then an off-the-shelf triangulation meshes what was kept.
A mesh is small next to a scan, so it is simplified whole, in this process: no tiles, no Dask.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import trimesh

from model.meshes import MESH_SUFFIXES, load_mesh, mesh_name
from model.methods import Method
from model.rules import kept_count
from model.selection import Tile
from pipeline.config import RunConfig
from pipeline.errors import PipelineError, raise_stop_behind
from pipeline.io.atomic import atomic_output
from pipeline.io.output_guard import check_output

MESH_OUTPUTS = (".ply", ".obj", ".off")
BALL_RADII = (1.5, 3.0, 6.0)  # ball radii in multiples of the kept points' mean nearest-neighbour spacing
NORMAL_NEIGHBOURS = 16  # points per PCA normal, and the tangent-plane graph that orients them
MIN_VERTICES = 4  # the fewest kept points that can close a surface


@dataclass(frozen=True)
class MeshReport:
    """What a mesh run did: where it wrote, vertices in and out, triangles made, how long."""

    output: Path
    input_vertices: int
    output_vertices: int
    triangles: int
    seconds: float

    def summary(self) -> str:
        """One line for the terminal."""
        return (f"{self.output}: {self.output_vertices:,} of {self.input_vertices:,} vertices, "
                f"{self.triangles:,} triangles ({self.seconds:.1f} s)")


def run_mesh(inputs: Sequence[Path], output: Path | None, config: RunConfig, overwrite: bool = False) -> MeshReport:
    """Simplify one mesh file to round(ratio * V) vertices, re-triangulated, written to `output` atomically.

    Every kept vertex is written, even one that ball pivoting left without a triangle, so the vertex
    count is exact; `<name>.simplified.ply` in the current folder is the default output.
    """
    start = time.perf_counter()
    config = config.validated()
    if len(inputs) != 1:
        raise PipelineError(f"--mesh takes one mesh file, got {len(inputs)} inputs")
    source = Path(inputs[0])
    output = Path(output) if output is not None else Path.cwd() / f"{mesh_name(source)}.simplified.ply"
    check_output(output, [source], overwrite, MESH_OUTPUTS)
    vertices, faces = read_mesh(source)
    count = kept_count(config.ratio, len(vertices))
    if count < MIN_VERTICES:
        raise PipelineError(f"{source}: --ratio {config.ratio} keeps {count} of {len(vertices)} vertices; "
                            f"triangulating needs at least {MIN_VERTICES}")
    kept = simplify_vertices(vertices, faces, config.simplifier, count, config.seed)
    triangles = ball_pivot(kept)
    with atomic_output(output) as temporary, open(temporary, "wb") as stream:
        trimesh.Trimesh(kept, triangles, process=False).export(stream, file_type=output.suffix.lower()[1:])
    return MeshReport(output, len(vertices), len(kept), len(triangles), time.perf_counter() - start)


def read_mesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (float64) and triangles of a mesh file; a missing, unreadable or faceless one is a PipelineError."""
    if not path.is_file():
        raise PipelineError(f"{path}: no such mesh file")
    if not path.name.lower().endswith(MESH_SUFFIXES):
        raise PipelineError(f"{path}: not a mesh file (use {', '.join(MESH_SUFFIXES)})")
    try:
        mesh = load_mesh(path)
        vertices = np.asarray(mesh.vertices, dtype=np.float64)
        faces = np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 3)
    except Exception as exc:  # trimesh's parsers raise anything from ValueError to IndexError on bad files
        reason = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise PipelineError(f"{path}: not a readable mesh ({reason})") from None
    if len(faces) == 0:
        raise PipelineError(f"{path}: no triangles (for a point cloud, run without --mesh)")
    if faces.min() < 0 or faces.max() >= len(vertices) or not np.isfinite(vertices).all():
        raise PipelineError(f"{path}: faces name missing vertices or coordinates are not finite")
    return vertices, faces


def simplify_vertices(vertices: np.ndarray, faces: np.ndarray, method: Method, count: int, seed: int) -> np.ndarray:
    """`count` kept vertex positions by `method`, the mesh treated as one centred tile of core points (the
    paper's GNN aggregates over the mesh adjacency there, as the paper does for meshes: Paper.on_mesh)."""
    centre = vertices.mean(axis=0)
    tile = Tile(vertices - centre, np.ones(len(vertices), dtype=bool), centre, seed)
    return method.on_mesh(tile, count, faces).xyz + centre


def ball_pivot(points: np.ndarray) -> np.ndarray:
    """(m, 3) triangles over `points` (indices into them) by open3d's ball pivoting.

    Normals are PCA over 16 nearest kept points, oriented consistently over their tangent-plane graph;
    balls of 1.5, 3 and 6 times the mean nearest-neighbour spacing roll in turn, the larger ones
    closing the gaps a feature-dense, smooth-sparse selection leaves.
    """
    o3d = _open3d()
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    spacing = float(np.mean(cloud.compute_nearest_neighbor_distance()))
    if not spacing > 0:  # every kept vertex at one place: no ball rolls over them, nothing to triangulate
        return np.empty((0, 3), dtype=np.int64)
    neighbours = min(NORMAL_NEIGHBOURS, len(points) - 1)
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(neighbours))
    try:
        cloud.orient_normals_consistent_tangent_plane(neighbours)
    except RuntimeError:  # Qhull's 3-D Delaunay fails on flat points (a terrain patch, a facade, a CAD face):
        cloud.orient_normals_to_align_with_direction(flattest_direction(points))  # one side of the plane for all
    radii = o3d.utility.DoubleVector([spacing * factor for factor in BALL_RADII])
    mesh = o3d.geometry.TriangleMesh.create_from_point_cloud_ball_pivoting(cloud, radii)
    if not np.array_equal(np.asarray(mesh.vertices), points):
        raise RuntimeError("ball pivoting re-ordered the points; triangle indices would not match")
    return np.asarray(mesh.triangles, dtype=np.int64).reshape(-1, 3)


def flattest_direction(points: np.ndarray) -> np.ndarray:
    """(3,) unit direction in which (m, 3) points spread least: a flat set's normal."""
    return np.linalg.eigh(np.cov(points.T))[1][:, 0]


def _open3d():
    """open3d, imported on first use (312 MB; only mesh mode needs it), or a one-line install hint."""
    try:
        import open3d
    except (ImportError, OSError) as exc:  # OSError: libusb-1.0 missing on a bare machine
        raise_stop_behind(exc)  # Ctrl-C in open3d's start comes back as an ImportError
        raise PipelineError(f"mesh mode needs open3d: pip install 'lidar-simplify[mesh]' ({exc})") from None
    return open3d
