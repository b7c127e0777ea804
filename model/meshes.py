"""Meshes: loading (.off, .off.gz, .obj, .ply), the per-class pose split and the mesh graph."""
from __future__ import annotations

import gzip
import re
from pathlib import Path

import numpy as np
import trimesh
from scipy import sparse

from model.geometry import knn

MESH_SUFFIXES = (".off", ".off.gz", ".obj", ".ply")


def mesh_name(path: Path) -> str:
    """File name without the mesh suffix (`cat0.off.gz` -> `cat0`)."""
    for suffix in MESH_SUFFIXES:
        if path.name.endswith(suffix):
            return path.name[: -len(suffix)]
    return path.stem


def shape_class(name: str) -> str:
    """TOSCA's class of a pose: the name without its trailing pose number (`michael12` -> `michael`)."""
    return re.sub(r"\d+$", "", name)


def load_mesh(path: Path) -> trimesh.Trimesh:
    """A triangle mesh as stored (no merging or re-ordering of vertices).

    maintain_order keeps an OBJ's `v` lines as its vertices: without it, faces that give per-corner
    normals (`f 1//1 2//1 3//1`) become a triangle soup with one vertex per corner.
    """
    if path.name.endswith(".gz"):
        with gzip.open(path) as stream:
            return trimesh.load(stream, file_type=path.name[:-3].rsplit(".", 1)[-1], process=False,
                                maintain_order=True)
    return trimesh.load(path, process=False, force="mesh", maintain_order=True)


def list_meshes(folder: Path) -> list[Path]:
    """Mesh files of a folder, sorted by name."""
    return sorted(p for p in folder.iterdir() if p.name.endswith(MESH_SUFFIXES))


def stratified_split(names: list[str], test_share: float = 0.2, seed: int = 0) -> tuple[list[str], list[str]]:
    """Train/test split by pose within each class (poses of a class share connectivity), as the paper does:
    round(test_share * poses) of each class, at least one, chosen by a seeded permutation."""
    rng = np.random.default_rng(seed)
    train, test = [], []
    for cls in sorted({shape_class(n) for n in names}):
        poses = sorted(n for n in names if shape_class(n) == cls)
        held = max(1, int(round(test_share * len(poses)))) if len(poses) > 1 else 0
        chosen = set(rng.permutation(poses)[:held].tolist())
        test += [p for p in poses if p in chosen]
        train += [p for p in poses if p not in chosen]
    return train, test


def mesh_graph(vertices: np.ndarray, faces: np.ndarray, width: int) -> np.ndarray:
    """(V, width) neighbour rows over mesh adjacency, each vertex first: the graph the paper's GNN uses on meshes.

    The network's mean operator needs rows of one width, so each row lists the vertex's 1-ring, then its
    2-ring, each nearest first, cut at width - 1; rows still short (borders, unreferenced or tiny
    meshes) are filled with the nearest other vertices by distance, as the kNN graph would have them.
    """
    n = len(vertices)
    width = min(width, n)
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).astype(np.int64)
    ring = sparse.csr_matrix((np.ones(len(edges), dtype=np.float32), (edges[:, 0], edges[:, 1])), shape=(n, n))
    ring = ((ring + ring.T) > 0).astype(np.float32)
    fill = knn(vertices, width).indices
    hops = [ring.nonzero(), (ring @ ring).nonzero(), (np.repeat(np.arange(n), width), fill.ravel())]
    rows = np.concatenate([r for r, _ in hops])
    cols = np.concatenate([c for _, c in hops])
    hop = np.concatenate([np.full(len(r), level) for level, (r, _) in enumerate(hops)])
    other = rows != cols
    rows, cols, hop = rows[other], cols[other], hop[other]
    order = np.lexsort((hop, cols, rows))  # one entry per (vertex, neighbour): its fewest hops
    rows, cols, hop = rows[order], cols[order], hop[order]
    first = np.r_[True, (rows[1:] != rows[:-1]) | (cols[1:] != cols[:-1])]
    rows, cols, hop = rows[first], cols[first], hop[first]
    distance = np.linalg.norm(vertices[rows] - vertices[cols], axis=1)
    order = np.lexsort((distance, hop, rows))
    rows, cols = rows[order], cols[order]
    rank = np.arange(len(rows)) - np.searchsorted(rows, rows)  # position within the vertex's row
    take = rank < width - 1
    graph = np.empty((n, width), dtype=np.int64)
    graph[:, 0] = np.arange(n)
    graph[rows[take], 1 + rank[take]] = cols[take]
    return graph
