"""`pipeline eval`: every quality metric (model/metrics.py) of simplified clouds against their reference.

Big scans are evaluated on a sample: whole XY grid cells of the reference (about 256 cells over its box),
drawn in seeded random order until they hold `sample` reference points. Both clouds are loaded on
those cells grown by a margin (SAMPLE_MARGIN of a cell side) and scored on the points inside the cells
only: margin points are neighbours and nearest points, so a point at a cell border is scored as in the
whole scan wherever its nearest point in the other cloud is closer than the margin. `--sample 0`
scores every point.
"""
from __future__ import annotations

import numbers
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Sequence

import numpy as np

from model.geometry import PointFeatures, point_features
from model.metrics import Quality, quality
from pipeline.apps.defaults import DEFAULT_SAMPLE
from pipeline.errors import PipelineError
from pipeline.io.crs import LengthUnit
from pipeline.io.points import (Cells, chunk_count, covering_grid, crs_of, length_unit_of, load_xyz, point_count,
                                xyz_chunks)
from pipeline.progress import Progress

if TYPE_CHECKING:
    import pyproj

SAMPLE_CELLS = 256
SAMPLE_MARGIN = 0.1  # of a cell side: how far around the sample cells both clouds are loaded
# (column title, Quality field, format): one definition for the eval and compare tables
METRIC_COLUMNS = (("CD", "chamfer", ".4g"), ("Hausdorff", "hausdorff", ".4g"), ("NC", "normal_consistency", ".4f"),
                  ("CE", "curvature_error", ".4f"), ("RE", "roughness_error", ".4f"), ("SDM", "sdm", ".4f"))


@dataclass(frozen=True)
class Reference:
    """The reference as evaluated: its (cropped, centred) points and their features, computed once;
    `scored` marks the points inside the sample cells (None: all, no sample)."""

    path: Path
    points: int
    cells: Cells | None
    centre: np.ndarray
    xyz: np.ndarray
    features: PointFeatures
    scored: np.ndarray | None
    unit: LengthUnit  # the reference's horizontal unit: of Hausdorff, and squared of CD
    crs: pyproj.CRS | None  # the reference's CRS, which every candidate must share (crs_of)

    @property
    def evaluated_points(self) -> int:
        """Reference points the metrics cover."""
        return len(self.xyz) if self.scored is None else int(self.scored.sum())


@dataclass(frozen=True)
class Score:
    """One candidate's metrics: points in its file, points evaluated (inside the sample cells)."""

    path: Path
    points: int
    evaluated_points: int
    quality: Quality


def check_sample(sample: int) -> None:
    """--sample is a number of reference points, 0 for every point."""
    if isinstance(sample, bool) or not isinstance(sample, numbers.Integral) or sample < 0:
        raise PipelineError(f"--sample must be a whole number of points, 0 (every point) or more, got {sample!r}")


def sample_cells(path: Path, sample: int, seed: int,
                 on_chunk: Callable[[int], None] = lambda points: None) -> Cells | None:
    """Seeded whole grid cells holding at least `sample` points of `path`; None when it has no more than that."""
    if sample <= 0 or point_count(path) <= sample:
        return None
    lows, highs = zip(*((xyz.min(axis=0), xyz.max(axis=0)) for xyz in xyz_chunks(path, on_chunk)))
    grid = covering_grid(np.min(lows, axis=0), np.max(highs, axis=0), SAMPLE_CELLS)
    counts = np.zeros(grid.shape[0] * grid.shape[1], dtype=np.int64)
    for xyz in xyz_chunks(path, on_chunk):
        counts += np.bincount(grid.keys(xyz), minlength=len(counts))
    order = np.random.default_rng(seed).permutation(np.flatnonzero(counts))
    taken = int(np.searchsorted(np.cumsum(counts[order]), sample)) + 1
    return Cells(grid.origin, grid.side, grid.shape, np.sort(order[:taken]))


def prepare_reference(path: Path, sample: int = DEFAULT_SAMPLE, seed: int = 0,
                      progress: Progress = Progress()) -> Reference:
    """Load the reference (or its sample cells), centre it and compute its features once for every candidate."""
    passes = 3 if 0 < sample < point_count(path) else 1  # sampling reads it twice to choose cells, then loads them
    with progress.phase(f"read {path.name}", passes * chunk_count(path), unit="chunk") as phase:
        cells = sample_cells(path, sample, seed, lambda points: phase.update(1, points))
        xyz, scored = load_sample(path, cells, lambda points: phase.update(1, points))
    centre = xyz.mean(axis=0)
    xyz = xyz - centre  # kd-trees and covariances on centred coordinates (DESIGN: traps)
    return Reference(path, point_count(path), cells, centre, xyz, point_features(xyz), scored, length_unit_of(path),
                     crs_of(path))


def load_sample(path: Path, cells: Cells | None,
                on_chunk: Callable[[int], None] = lambda points: None) -> tuple[np.ndarray, np.ndarray | None]:
    """A file's points on the sample cells grown by the margin, and the mask of those inside the cells
    (all points and None without a sample)."""
    if cells is None:
        return load_xyz(path, on_chunk=on_chunk), None
    xyz = load_xyz(path, cells, SAMPLE_MARGIN * cells.side, on_chunk)
    return xyz, cells.contains(xyz)


def score(reference: Reference, path: Path) -> Score:
    """Metrics of one candidate file against the prepared reference, on the same cells; a candidate whose
    CRS is in another unit (its distances would mix feet and metres) or is another CRS is refused."""
    unit = length_unit_of(path)
    if not (unit.assumed or reference.unit.assumed) and unit.name != reference.unit.name:
        raise PipelineError(f"{path}: its coordinates are in {unit.name} and {reference.path}'s in "
                            f"{reference.unit.name}: reproject one first (e.g. pdal translate with filters.reprojection)")
    theirs, ours = crs_of(path), reference.crs
    if theirs is not None and ours is not None and not theirs.equals(ours, ignore_axis_order=True):
        raise PipelineError(f"{path}: its CRS {theirs.name!r} is not {reference.path}'s ({ours.name!r}): the same "
                            "coordinates mean other places; reproject one first (e.g. pdal translate with "
                            "filters.reprojection)")
    xyz, scored = load_sample(path, reference.cells)
    evaluated = len(xyz) if scored is None else int(scored.sum())
    if evaluated == 0 or not overlaps(reference.xyz, xyz - reference.centre):
        crs_note = " (one of them has no CRS: are they in the same one?)" if (theirs is None) != (ours is None) else ""
        raise PipelineError(f"{path}: no points where {reference.path} was evaluated{crs_note}")
    return Score(path, point_count(path), evaluated,
                 quality(reference.xyz, xyz - reference.centre, reference.features, reference.scored, scored))


def overlaps(reference: np.ndarray, candidate: np.ndarray, margin: float = 0.01) -> bool:
    """Whether the bounding boxes of two (n, 3) clouds meet, within `margin` of the reference's diagonal: a
    simplification of the reference lies inside it; one that does not is another place (or CRS)."""
    low, high = reference.min(axis=0), reference.max(axis=0)
    reach = margin * float(np.linalg.norm(high - low))
    return bool(((candidate.min(axis=0) <= high + reach) & (candidate.max(axis=0) >= low - reach)).all())


def evaluate(reference_path: Path, candidates: Sequence[Path], sample: int = DEFAULT_SAMPLE,
             seed: int = 0, progress: Progress = Progress()) -> tuple[Reference, list[Score]]:
    """Prepare the reference once, then score every candidate against it."""
    check_sample(sample)
    for path in (reference_path, *candidates):
        if not path.exists():
            raise PipelineError(f"{path}: no such file")
    reference = prepare_reference(reference_path, sample, seed, progress)
    scores = []
    with progress.phase("score candidates", len(candidates), unit="file") as phase:
        for path in candidates:
            scores.append(score(reference, path))
            phase.update(1, scores[-1].points)
    return reference, scores


def metric_cells(q: Quality) -> list[str]:
    """The metric columns of one table row."""
    return [format(getattr(q, field), spec) for _, field, spec in METRIC_COLUMNS]


def markdown_table(titles: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    """A Markdown table, first column left-aligned and the others right-aligned."""
    lines = ["| " + " | ".join(titles) + " |", "| --- |" + " ---: |" * (len(titles) - 1)]
    return "\n".join(lines + ["| " + " | ".join(row) + " |" for row in rows])


def sample_note(reference: Reference) -> str:
    """One line saying what part of the reference the metrics cover."""
    share = "all points" if reference.cells is None else f"{len(reference.cells.chosen)} sampled grid cells"
    return (f"reference {reference.path}: {reference.points:,} points; evaluated on {reference.evaluated_points:,} "
            f"({share}); Hausdorff in {reference.unit.label}, CD (squared distances) in square {reference.unit.name}; "
            "lower is better for every metric")


def format_scores(reference: Reference, scores: Sequence[Score]) -> str:
    """The `pipeline eval` table: one row per candidate."""
    titles = ["candidate", "points", *(title for title, _, _ in METRIC_COLUMNS)]
    rows = [[str(s.path), f"{s.points:,}", *metric_cells(s.quality)] for s in scores]
    return sample_note(reference) + "\n\n" + markdown_table(titles, rows)


def reference_json(reference: Reference) -> dict[str, Any]:
    """What the JSON outputs say about the reference and the sample."""
    return {"reference": str(reference.path), "reference_points": reference.points,
            "evaluated_reference_points": reference.evaluated_points,
            "sample_cells": None if reference.cells is None else len(reference.cells.chosen),
            "length_unit": reference.unit.name, "length_unit_assumed": reference.unit.assumed}


def score_json(s: Score) -> dict[str, Any]:
    """One candidate's JSON record: its path, point counts and every metric."""
    return {"path": str(s.path), "points": s.points, "evaluated_points": s.evaluated_points, **asdict(s.quality)}
