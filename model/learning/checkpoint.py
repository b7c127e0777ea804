"""Loading shipped weights into a network: one place for the missing-file message and the CPU map."""
from __future__ import annotations

from pathlib import Path
from typing import TypeVar

import torch
from torch import nn

Module = TypeVar("Module", bound=nn.Module)


def load_trained(module: Module, path: Path, train_command: str) -> Module:
    """`module` with the state dict saved at `path` (as training writes it), in inference mode."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no trained weights (train them with `{train_command}`)")
    module.load_state_dict(torch.load(path, map_location="cpu", weights_only=True)["state_dict"])
    return module.eval()
