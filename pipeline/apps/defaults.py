"""Defaults that the command line's help shows, apart from the code that uses them: `pipeline run` then imports
neither the scoring nor the report code (13-18 ms of every run, measured as 20 imports of the command line)."""
from __future__ import annotations

DEFAULT_SAMPLE = 200_000  # source points `eval`, `compare` and `report` score on (0: every point)
COLORS = ("elevation", "classification", "rgb")  # what may colour the report's 3-D points
