"""Training the learned simplifier on TOSCA-style meshes (`pipeline train`), CPU-friendly.

Each step takes one training mesh, draws `points` of its vertices at random (the stand-in for a tile;
fresh each epoch, so epochs also augment), builds the k=16 kNN graph the pipeline will use at
inference, draws a ratio in [0.05, 0.8], and minimises adaptive Chamfer + lambda * CE between the
drawn points and the refined centres. Adam, lr 1e-3, learning rate x0.99 per epoch.
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from tqdm import tqdm

from model.learning.losses import mean_curvature, total_loss
from model.learning.network import LearnedSimplifier, knn_graph, normalise
from model.learning.saving import saved_together
from model.meshes import list_meshes, load_mesh, mesh_name, stratified_split

CHECKPOINT_EVERY = 10  # epochs; a long run killed midway keeps its last checkpoint


@dataclass
class TrainSettings:
    """Every training hyper-parameter; saved with the weights."""

    epochs: int = 150
    points: int = 2048
    ratio_min: float = 0.05
    ratio_max: float = 0.8
    learning_rate: float = 1e-3
    decay: float = 0.99
    curvature_weight: float = 0.1
    seed: int = 0
    test_share: float = 0.2


@dataclass
class TrainRecord:
    """What training produced besides the weights: split, per-epoch mean losses, time."""

    settings: dict
    train: list[str]
    test: list[str]
    history: list[dict] = field(default_factory=list)
    seconds: float = 0.0


def training_step(model: LearnedSimplifier, vertices: np.ndarray, settings: TrainSettings,
                  rng: np.random.Generator) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Loss of one random draw of a mesh's vertices at one random ratio."""
    chosen = rng.choice(len(vertices), size=min(settings.points, len(vertices)), replace=False)
    xyz, _, _ = normalise(torch.from_numpy(vertices[chosen].astype(np.float32)))
    count = max(1, int(round(rng.uniform(settings.ratio_min, settings.ratio_max) * len(xyz))))
    _, refined = model(xyz, knn_graph(xyz.numpy()), count, int(rng.integers(len(xyz))))
    with torch.no_grad():
        source_curvature = mean_curvature(xyz)
    return total_loss(xyz, source_curvature, refined, settings.curvature_weight)


def train(data: Path, out: Path, settings: TrainSettings, show_progress: bool = True,
          log: Callable[[str], None] = lambda line: None) -> TrainRecord:
    """Train on the meshes in `data`, save weights and record to `out`; returns the record."""
    started = time.perf_counter()
    torch.manual_seed(settings.seed)
    rng = np.random.default_rng(settings.seed)
    paths = {mesh_name(p): p for p in list_meshes(data)}
    train_names, test_names = stratified_split(sorted(paths), settings.test_share, settings.seed)
    meshes = {name: np.asarray(load_mesh(paths[name]).vertices, dtype=np.float64) for name in train_names}
    record = TrainRecord(asdict(settings), train_names, test_names)
    model = LearnedSimplifier()
    optimiser = torch.optim.Adam(model.parameters(), lr=settings.learning_rate)
    schedule = torch.optim.lr_scheduler.ExponentialLR(optimiser, gamma=settings.decay)
    bar = tqdm(range(settings.epochs), desc="train", unit="epoch", disable=not show_progress)
    for epoch in bar:
        model.train()
        sums = np.zeros(3)
        for name in rng.permutation(train_names):
            loss, chamfer, error = training_step(model, meshes[name], settings, rng)
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
            sums += [loss.item(), chamfer.item(), error.item()]
        schedule.step()
        mean = sums / len(train_names)
        record.history.append({"epoch": epoch + 1, "loss": float(mean[0]), "chamfer": float(mean[1]),
                               "curvature_error": float(mean[2])})
        summary = f"loss {mean[0]:.5f} (CD {mean[1]:.5f}, CE {mean[2]:.4f})"
        bar.set_postfix_str(summary)
        log(f"epoch {epoch + 1}/{settings.epochs}: {summary}, lr {schedule.get_last_lr()[0]:.6f}")
        record.seconds = time.perf_counter() - started
        if (epoch + 1) % CHECKPOINT_EVERY == 0 or epoch + 1 == settings.epochs:
            save_weights(out, model, record)
    return record


def save_weights(out: Path, model: LearnedSimplifier, record: TrainRecord) -> None:
    """One small .pt file: the state dict and the training record (settings, split, losses)."""
    saved_together([(out, lambda path: torch.save({"state_dict": model.state_dict(), "record": asdict(record)},
                                                  path))])
