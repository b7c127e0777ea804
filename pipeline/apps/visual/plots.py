"""Figures for `pipeline compare`: each metric against the ratio, and one region seen per method.

matplotlib's object API (Figure, no pyplot) renders with Agg and keeps no global state, so it works on
machines without a display and inside long-lived processes.
"""
from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
from matplotlib.figure import Figure

AZIMUTH, ELEVATION = np.radians(-35.0), np.radians(35.0)  # oblique view: facades and poles stay visible
MARKER_BUDGET = 3_000  # marker area (points^2) shared by a panel's dots


def metric_plot(values: Mapping[str, Mapping[float, float]], title: str, path: Path) -> Path:
    """One line per method of a metric against the ratio kept (log axis: ratios halve)."""
    figure = Figure(figsize=(5, 3.6), layout="constrained")
    axes = figure.add_subplot()
    for method, by_ratio in values.items():
        ratios = sorted(by_ratio)
        axes.plot(ratios, [by_ratio[r] for r in ratios], marker="o", label=method)
    axes.set_xscale("log")
    axes.set_xticks(sorted({r for by_ratio in values.values() for r in by_ratio}))
    axes.xaxis.set_major_formatter("{x:g}")
    axes.xaxis.set_minor_formatter("")
    axes.set(xlabel="ratio kept", ylabel=title, title=f"{title} (lower is better)")
    axes.legend(fontsize="small")
    figure.savefig(path, dpi=110)
    return path


def oblique(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Screen u, v and depth of points seen from above one side (larger depth is farther)."""
    x, y, z = xyz.T
    across = x * np.sin(AZIMUTH) + y * np.cos(AZIMUTH)
    u = x * np.cos(AZIMUTH) - y * np.sin(AZIMUTH)
    v = z * np.cos(ELEVATION) + across * np.sin(ELEVATION)
    return u, v, across * np.cos(ELEVATION) - z * np.sin(ELEVATION)


Panel = tuple[np.ndarray, np.ndarray]  # xyz, mean curvature


def region_view(reference: Panel, panels: Mapping[tuple[str, float], Panel], methods: Sequence[str],
                ratios: Sequence[float], path: Path) -> Path:
    """A grid of oblique views of one region coloured by mean curvature: a row per ratio, the reference
    first and then a column per method; one colour scale (up to the reference's 98th percentile)."""
    figure = Figure(figsize=(3.2 * (len(methods) + 1), 3.0 * len(ratios)), layout="constrained")
    grid = figure.subplots(len(ratios), len(methods) + 1, squeeze=False, sharex=True, sharey=True)
    vmax = float(np.percentile(reference[1], 98)) if len(reference[1]) else 1.0
    image = None
    for row, ratio in enumerate(ratios):
        cells = [("reference", reference)] + [(f"{m} {ratio:g}", panels[(m, ratio)]) for m in methods]
        for axes, (title, (xyz, curvature)) in zip(grid[row], cells):
            u, v, depth = oblique(xyz)
            order = np.argsort(-depth)  # far first, so near points are drawn on top
            size = float(np.clip(MARKER_BUDGET / max(len(xyz), 1), 0.5, 4))  # sparse panels get bigger dots
            image = axes.scatter(u[order], v[order], c=curvature[order], s=size, cmap="viridis", vmin=0,
                                 vmax=vmax or 1.0, linewidths=0)
            axes.set_title(f"{title} ({len(xyz):,} pts)" if len(xyz) else f"{title}: no points here", fontsize="small")
            axes.set_aspect("equal")
            axes.set_xticks([])
            axes.set_yticks([])
    figure.colorbar(image, ax=grid, shrink=0.6, label="mean curvature")
    figure.savefig(path, dpi=110)
    return path
