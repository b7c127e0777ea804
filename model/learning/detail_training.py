"""Training the curvature-loss predictor (model/detail.py) on TOSCA shapes sampled as a scanner samples.

A scan is not a mesh's vertices: a scanner sees one side of an object from one place, its density falls
with range and obliquity, it leaves stripes along its scan lines and it adds range noise. Each training
cloud is one such view of a training mesh (scanner_view): 20k-80k points, the same size as a tile.
For each cloud and a random ratio in [0.05, 0.3], the target is the curvature loss that an even
(stratified) thinning to that ratio, at a random phase, makes at each point, over its mean
(model.stratified.curvature_loss); the network sees the full cloud's descriptors and the loss of the one
thinning inference measures (phase 0.5), so it learns the expected loss: a denoised measurement. The split is the paper weights' (model/meshes.py:
by pose within each class, seed 0), so no test pose is ever seen.
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import trimesh

from model.detail import descriptors, relative
from model.learning.detail_net import DetailNet, export_weights
from model.learning.saving import saved_together
from model.meshes import list_meshes, load_mesh, mesh_name, stratified_split
from model.rules import kept_count
from model.selection import Tile
from model.stratified import curvature_loss


@dataclass(frozen=True)
class DetailSettings:
    """Every setting of a training run; saved with the weights."""

    views_per_mesh: int = 3
    points_min: int = 20_000
    points_max: int = 80_000
    ratio_min: float = 0.05
    ratio_max: float = 0.3
    rows_per_view: int = 20_000  # rows drawn from each view for training
    epochs: int = 12
    batch: int = 4096
    learning_rate: float = 2e-3
    seed: int = 0
    test_share: float = 0.2
    target_cap: float = 20.0  # relative losses above this are clipped (a few isolated points)


def scanner_view(mesh: trimesh.Trimesh, points: int, rng: np.random.Generator) -> np.ndarray:
    """(m, 3) points of the mesh as one scanner position sees it (m about `points`, centred).

    Faces turned away from the scanner are not seen; a seen face is sampled in proportion to its area
    times the cosine of incidence over the squared range; scan lines keep points where a cosine of the
    distance along a random direction is high; range noise moves each point along the line of sight.
    """
    centre = mesh.vertices.mean(axis=0)
    radius = float(np.linalg.norm(mesh.vertices - centre, axis=1).max())
    direction = rng.normal(size=3)
    scanner = centre + direction / np.linalg.norm(direction) * radius * rng.uniform(2.0, 4.0)
    to_scanner = scanner - mesh.triangles_center
    distance = np.linalg.norm(to_scanner, axis=1)
    cosine = np.einsum("ij,ij->i", mesh.face_normals, to_scanner) / np.maximum(distance, 1e-12)
    weight = np.where(cosine > 0.05, mesh.area_faces * cosine / distance**2, 0.0)
    if weight.sum() <= 0:
        weight = mesh.area_faces.copy()
    faces = rng.choice(len(weight), size=points * 2, p=weight / weight.sum())
    corners = mesh.triangles[faces]
    u, v = rng.random((2, len(faces)))
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    xyz = corners[:, 0] + u[:, None] * (corners[:, 1] - corners[:, 0]) + v[:, None] * (corners[:, 2] - corners[:, 0])
    spacing = np.sqrt(mesh.area.sum() / 2 / points)
    across = rng.normal(size=3)
    stripes = 0.5 * (1 + np.cos(2 * np.pi * (xyz @ (across / np.linalg.norm(across))) / (spacing * rng.uniform(2, 6))))
    kept = xyz[rng.random(len(xyz)) < 0.25 + 0.75 * stripes]
    kept = kept[rng.permutation(len(kept))[:points]]
    sight = kept - scanner
    sight /= np.linalg.norm(sight, axis=1, keepdims=True)
    kept = kept + sight * rng.normal(0, rng.uniform(0.0, 0.3) * spacing, size=(len(kept), 1))
    return kept - kept.mean(axis=0)


def training_rows(xyz: np.ndarray, ratio: float, rows: int, cap: float,
                  rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Descriptors (rows, 12) and relative curvature loss (rows,) of a random subset of one view's points."""
    tile = Tile(xyz, np.ones(len(xyz), dtype=bool), np.zeros(3), seed=0)
    budget = kept_count(ratio, len(xyz))
    features = descriptors(tile, budget)  # with the loss of the thinning inference measures (phase 0.5)
    target = relative(curvature_loss(tile, budget, phase=float(rng.uniform(0, 1)), here=features[:, 2]), cap)
    chosen = rng.choice(len(xyz), size=min(rows, len(xyz)), replace=False)
    return features[chosen], target[chosen].astype(np.float32)


def make_dataset(paths: list[Path], settings: DetailSettings, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Rows from `views_per_mesh` scanner views of each mesh."""
    features, targets = [], []
    for path in paths:
        mesh = load_mesh(path)
        for _ in range(settings.views_per_mesh):
            xyz = scanner_view(mesh, int(rng.integers(settings.points_min, settings.points_max)), rng)
            ratio = float(rng.uniform(settings.ratio_min, settings.ratio_max))
            f, t = training_rows(xyz, ratio, settings.rows_per_view, settings.target_cap, rng)
            features.append(f)
            targets.append(t)
    return np.concatenate(features), np.concatenate(targets)


def train_detail(data: Path, out: Path, settings: DetailSettings = DetailSettings(), log=print) -> dict:
    """Train on the training split of the meshes in `data`, write weights and record to `out` (and the weights as
    numpy arrays beside it, `out` with suffix .npz); return the record."""
    started = time.perf_counter()
    torch.manual_seed(settings.seed)
    rng = np.random.default_rng(settings.seed)
    paths = list_meshes(data)
    train_names, test_names = stratified_split([mesh_name(p) for p in paths], settings.test_share, settings.seed)
    by_name = {mesh_name(p): p for p in paths}
    features, targets = make_dataset([by_name[n] for n in train_names], settings, rng)
    test_features, test_targets = make_dataset([by_name[n] for n in test_names], settings, rng)
    log(f"{len(features):,} training rows from {len(train_names)} meshes, {len(test_features):,} test rows "
        f"({time.perf_counter() - started:.0f} s)")
    net = DetailNet()
    net.shift.copy_(torch.from_numpy(features.mean(axis=0)))
    net.spread.copy_(torch.from_numpy(features.std(axis=0) + 1e-6))
    optimiser = torch.optim.Adam(net.parameters(), lr=settings.learning_rate)
    x, y = torch.from_numpy(features), torch.from_numpy(targets)
    history = []
    for epoch in range(settings.epochs):
        order = torch.randperm(len(x))
        total = 0.0
        for start in range(0, len(x), settings.batch):
            rows = order[start:start + settings.batch]
            loss = torch.mean((net(x[rows]) - y[rows]) ** 2)
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
            total += float(loss.detach()) * len(rows)
        for group in optimiser.param_groups:
            group["lr"] *= 0.8
        scores = evaluate(net, test_features, test_targets)
        history.append({"epoch": epoch + 1, "train_mse": total / len(x), **scores})
        log(f"epoch {epoch + 1}: train mse {total / len(x):.4f}, test mse {scores['test_mse']:.4f}, "
            f"test correlation {scores['test_correlation']:.3f}")
    record = {"settings": asdict(settings), "train": train_names, "test": test_names, "history": history,
              "seconds": time.perf_counter() - started}
    saved_together([(out, lambda path: torch.save({"state_dict": net.state_dict(), "record": record}, path)),
                    (out.with_suffix(".npz"), lambda path: export_weights(net, path))])  # what the default loads
    return record


@torch.no_grad()
def evaluate(net: DetailNet, features: np.ndarray, targets: np.ndarray) -> dict:
    """Mean squared error and Pearson correlation of the predictions on held-out rows."""
    predicted = net.eval()(torch.from_numpy(features)).numpy()
    net.train()
    return {"test_mse": float(np.mean((predicted - targets) ** 2)),
            "test_correlation": float(np.corrcoef(predicted, targets)[0, 1])}
