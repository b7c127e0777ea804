"""The curvature-loss predictor as a torch network, for training (model/learning/detail_training.py), and its export to
the numpy arrays the default method runs on (model.detail.DetailWeights)."""
from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np
import torch
from torch import nn

from model.detail import DESCRIPTORS, HIDDEN
from model.learning import WEIGHTS_DIR
from model.learning.checkpoint import load_trained

TRAINED = WEIGHTS_DIR / "detail.pt"


class DetailNet(nn.Module):
    """Descriptors (standardised by the training set's mean and deviation) -> predicted relative loss >= 0."""

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("shift", torch.zeros(DESCRIPTORS))
        self.register_buffer("spread", torch.ones(DESCRIPTORS))
        self.layers = nn.Sequential(nn.Linear(DESCRIPTORS, HIDDEN), nn.ReLU(), nn.Linear(HIDDEN, HIDDEN), nn.ReLU(),
                                    nn.Linear(HIDDEN, 1), nn.Softplus())

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return self.layers((features - self.shift) / self.spread).squeeze(-1)


@lru_cache(maxsize=2)
def load_detail_net(path: Path = TRAINED) -> DetailNet:
    """The trained network in inference mode."""
    return load_trained(DetailNet(), path, "pipeline train-detail")


def export_weights(net: DetailNet, path: Path) -> None:
    """Save the network's standardisation and dense layers as float32 arrays in an .npz (model.detail reads it)."""
    dense = [layer for layer in net.layers if isinstance(layer, nn.Linear)]
    arrays = {"shift": net.shift, "spread": net.spread,
              **{f"weight_{i}": layer.weight for i, layer in enumerate(dense)},
              **{f"bias_{i}": layer.bias for i, layer in enumerate(dense)}}
    with open(path, "wb") as file:
        np.savez(file, **{name: value.detach().numpy().astype(np.float32) for name, value in arrays.items()})
