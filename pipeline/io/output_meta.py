"""What every output writer receives besides the tiles' kept points (tiling.assemble.TilePart): what the run
records about itself."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np


@dataclass
class OutputMeta:
    """What an output records about the run besides the points (pipeline.io.provenance writes it down)."""

    crs_wkt: str | None
    sources: list[str]
    ratio: float
    method: str
    version: str
    settings: dict[str, Any] = field(default_factory=dict)  # the run's settings, JSON-able, lengths in metres
    trained_weights: Path | None = None  # the file of weights the method ran on


def priority_fraction(count: int) -> np.ndarray:
    """(count,) each record's place in a part's priority order as a fraction, (i + 0.5) / count: the first k %
    of every tile together are the scan's best k % (COPC levels and pipeline.simplify's order use it)."""
    return (np.arange(count) + 0.5) / max(count, 1)
