"""Tiles' cover counts past their survey's share of the count, where a run needs them: the hole cover's floors
at the run's radius, and the reference its Chamfer bound is held against, one farthest point sampling (FPS) of
the whole scan as the tiles stand for it.

Why the reference: the survey samples each tile's FPS at the tile's share of the count, and those samplings,
pooled, stood for one FPS of the whole scan only where density is even. Their mean squared distance came out
1.00-1.05x an untiled FPS's on the shared scans and 1.14-1.25x on a mobile street, whose sparse far tiles get
few picks for their area: a Chamfer bound of 1.3x them let a run reach 1.35x an untiled FPS (autzen at 0.2).
One FPS of the whole scan covers everywhere at about one radius: each tile's FPS run to the radius r* at which
the tiles' counts add up to the target gave the mean squared distance within -3.3 to +3.1 % of an untiled
FPS's on 27 scan-ratio pairs (bench/fps_reference.py). Rescaling each tile's distances at its share to its
count at r* instead was not enough (1.04x on autzen at 0.2, 1.07x on the street): they are measured.
"""
from __future__ import annotations

from concurrent.futures import Executor
from dataclasses import replace
from typing import TYPE_CHECKING, Callable

import numpy as np

from model.cover import grown_sample
from pipeline.config import RunConfig
from pipeline.engine.classes import ClassRule
from pipeline.engine.execute import map_tasks
from pipeline.engine.tasks import (CoverJob, FloorJob, ReferenceJob, TileSurvey, count_cover, exact_floor,
                                   reference_square, surveyed_picks)
from pipeline.engine.workdir import WorkDir
from pipeline.progress import Progress
from tiling.budgets import count_at, last_over, least_covers, one_radius_counts, radius_grid
from tiling.plan import TilePlan
from tiling.store import Slice

if TYPE_CHECKING:
    from dask.distributed import Client


def cover_floors(client: Client | Executor, plan: TilePlan, slices: list[list[Slice]], surveys: list[TileSurvey],
                 sizes: np.ndarray, radius: float, work: WorkDir, config: RunConfig, progress: Progress,
                 cache_bytes: int, cost: Callable[[CoverJob], int], counted: frozenset[int]) -> np.ndarray:
    """(tiles,) the fewest picks that leave no core point of each tile farther than `radius` from one: read from
    the radii its kept picks leave covered where they cover it there (in its survey's file, or in its cover
    count's for the `counted` tiles), or, where they fall short (a tile sparse for this radius), a count of the
    tile's own at the radius (a task that loads its core)."""
    radii = radius_grid(sizes)
    floors = count_at(np.array([survey.covers for survey in surveys]), radii, radius)
    kept = np.flatnonzero(floors >= 0)
    jobs = [FloorJob(kept_picks(work, int(tile_id), counted), radius, surveys[tile_id].core_count) for tile_id in kept]
    floors[kept] = map_tasks(client, exact_floor, jobs, desc="read floors", progress=progress)
    short = np.flatnonzero(floors < 0)
    if len(short):
        cover_jobs = [cover_job(plan, slices, surveys, radii, int(tile_id), (radius,), radius, work, config,
                                cache_bytes) for tile_id in short]
        counts = map_tasks(client, count_cover, cover_jobs, plan, desc="count covers", progress=progress, cost=cost)
        floors[short] = [int(count[0]) for count in counts]
    return floors


COUNT_ROUNDS = 8  # rounds of counts a reference may take (one in every run measured but a 0.5 m tiling's: two)


def fps_reference(client: Client | Executor, plan: TilePlan, slices: list[list[Slice]], surveys: list[TileSurvey],
                  sizes: np.ndarray, target: int, work: WorkDir, config: RunConfig, progress: Progress,
                  cache_bytes: int, cost: Callable[[CoverJob], int]) -> tuple[list[TileSurvey], float, frozenset[int]]:
    """The surveys with the cover counts of tiles short at r* counted past their share (exact from the grid
    radius below r* up), the mean squared distance from the tiles' samples to their FPS picks at r*, pooled by
    core points over the tiles with a trial fill (those the Chamfer estimate covers), and the tiles counted
    (their picks kept in work.cover_path). A tile with points but no share of the count (a few points: it
    has no trial fill) counts as one pick more than it sampled, none, towards r*."""
    radii = radius_grid(sizes)
    counts = np.array([survey.core_count for survey in surveys])
    measured = np.array([len(survey.gaps) > 0 for survey in surveys])
    if not measured.any():
        return surveys, 0.0, frozenset()
    least, counted, surveys = surveyed_least(surveys), frozenset(), list(surveys)
    for _ in range(COUNT_ROUNDS):  # a count can come out below the survey's placeholder (one more than it
        # sampled) and move the bracket to a finer radius, where other tiles are then short: count those too
        below = max(last_over(least, target), 0)  # r* lies past this grid radius (or below the grid: its first)
        short = np.flatnonzero(measured & (np.array([survey.covers[below] for survey in surveys]) < 0))
        if not len(short):
            break
        jobs = [cover_job(plan, slices, surveys, radii, int(tile_id), tuple(radii), float(radii[below]), work, config,
                          cache_bytes, keep=True) for tile_id in short]
        for tile_id, covers in zip(short, map_tasks(client, count_cover, jobs, plan, desc="count covers",
                                                    progress=progress, cost=cost)):
            surveys[tile_id] = replace(surveys[tile_id], covers=covers)
        least, counted = surveyed_least(surveys), counted | frozenset(short.tolist())
    picks = np.maximum(np.rint(one_radius_counts(least, target)), 1).astype(np.int64)
    tiles = np.flatnonzero(measured)
    jobs = [ReferenceJob(kept_picks(work, int(tile_id), counted), int(picks[tile_id])) for tile_id in tiles]
    squares = np.array(map_tasks(client, reference_square, jobs, desc="measure reference", progress=progress))
    return surveys, float((squares * counts[tiles]).sum() / counts[tiles].sum()), counted


def kept_picks(work: WorkDir, tile_id: int, counted: frozenset[int]) -> str:
    """The file holding a tile's farthest point picks, their radii and its sample: its cover count's where the
    run `counted` it past its survey's picks, else its survey's."""
    return str(work.cover_path(tile_id) if tile_id in counted else work.survey_path(tile_id))


def surveyed_least(surveys: list[TileSurvey]) -> np.ndarray:
    """(tiles, g) the least each tile's cover count can be at each radius of the survey's grid
    (tiling.budgets.least_covers: what its survey's picks counted, one more than them where they fell short)."""
    counts = [survey.core_count for survey in surveys]
    sampled = [surveyed_picks(survey.picks, count) for survey, count in zip(surveys, counts)]
    return least_covers(np.array([survey.covers for survey in surveys]), np.array(sampled), np.array(counts))


def cover_job(plan: TilePlan, slices: list[list[Slice]], surveys: list[TileSurvey], radii: np.ndarray, tile_id: int,
              counted_at: tuple[float, ...], finest: float, work: WorkDir, config: RunConfig, cache_bytes: int,
              keep: bool = False) -> CoverJob:
    """A count of the tile's own cover at `counted_at`, sampled until it covers at `finest` (its picks and sample
    kept in work.cover_path when `keep`)."""
    return CoverJob(str(work.store_path), tile_id, tuple(slices[tile_id]), cache_bytes,
                    first_sample(surveys[tile_id], radii, finest), counted_at, finest, config.seed,
                    ClassRule.of(config), str(work.cover_path(tile_id)) if keep else None)


def first_sample(survey: TileSurvey, radii: np.ndarray, radius: float) -> int:
    """The picks a tile's own cover count starts from: as many as the finest grid radius its survey's picks
    (tasks.surveyed_picks) covered at asks for to reach `radius` (model.cover.grown_sample), or the survey's
    picks again where they covered at none (their gap is then unknown)."""
    counted, sampled = radii[survey.covers >= 0], surveyed_picks(survey.picks, survey.core_count)
    return grown_sample(sampled, float(counted.min()), radius, survey.core_count) if len(counted) else sampled
