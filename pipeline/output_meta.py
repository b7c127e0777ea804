"""What every output writer receives: the tiles' kept points and what the run records about itself."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass(frozen=True)
class TilePart:
    """One tile's kept points, in output order, and their XY bounds (the core rectangle, grown to hold them)."""

    tile_id: int
    bounds: tuple[float, float, float, float]
    records: np.ndarray


@dataclass
class OutputMeta:
    """What an output records about the run besides the points (pipeline.provenance writes it down)."""

    crs_wkt: str | None
    sources: list[str]
    ratio: float
    method: str
    version: str
    settings: dict[str, Any] = field(default_factory=dict)  # the run's settings, JSON-able, lengths in metres


def priority_fraction(count: int) -> np.ndarray:
    """(count,) each record's place in a part's priority order as a fraction, (i + 0.5) / count: the first k %
    of every tile together are the scan's best k % (COPC levels and pipeline.simplify's order use it)."""
    return (np.arange(count) + 0.5) / max(count, 1)
