"""TOSCA-style training meshes: loading (.off, .off.gz, .obj, .ply) and the per-class pose split."""
from __future__ import annotations

import gzip
import re
from pathlib import Path

import numpy as np
import trimesh

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
    """A triangle mesh as stored (no merging or re-ordering of vertices)."""
    if path.name.endswith(".gz"):
        with gzip.open(path) as stream:
            return trimesh.load(stream, file_type=path.name[:-3].rsplit(".", 1)[-1], process=False)
    return trimesh.load(path, process=False, force="mesh")


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
