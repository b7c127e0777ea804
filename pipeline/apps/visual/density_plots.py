"""Kept-to-expected density maps drawn top-down: interactive (plotly heatmaps, for the HTML report) and as
one PNG (matplotlib, for Markdown). Both use one diverging, logarithmic scale centred on 1 (0.25 .. 4):
red where an output kept less than its share, blue where more, blank where the source has no point."""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np
import plotly.graph_objects as go
from matplotlib.colors import LogNorm
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator
from plotly.subplots import make_subplots

from pipeline.apps.visual.density_map import DensityMap

LOW, HIGH = 0.25, 4.0  # the scale's ends; ratios beyond are drawn at them
TICKS = (0.25, 0.5, 1.0, 2.0, 4.0)
COLOURMAP = "RdBu"  # matplotlib's and plotly's: red low, white 1, blue high


def columns_for(maps: Sequence[DensityMap]) -> int:
    """Panels per row: one for a long strip (a street), else up to three."""
    nx, ny = maps[0].grid.shape
    return 1 if nx > 2 * ny else min(3, len(maps))


def title(label: str, density: DensityMap) -> str:
    """A panel's title: the output and the share it kept."""
    return f"{label} (kept {density.kept_share:.3g} of the source)"


def density_figure(maps: Sequence[DensityMap], labels: Sequence[str], unit: str) -> go.Figure:
    """One heatmap per output of log2(kept / expected), hover showing the ratio itself; axes in `unit`."""
    columns = columns_for(maps)
    rows = -(-len(maps) // columns)
    figure = make_subplots(rows=rows, cols=columns, subplot_titles=list(map(title, labels, maps)),
                           horizontal_spacing=0.06, vertical_spacing=0.12 / rows)
    for number, density in enumerate(maps):
        x0, _, y0, _ = density.extent
        nx, ny = density.grid.shape
        side = density.grid.side
        cell = {"row": number // columns + 1, "col": number % columns + 1}
        figure.add_trace(go.Heatmap(
            z=np.log2(np.clip(density.ratio, LOW, HIGH)), customdata=density.ratio,
            x=x0 + (np.arange(nx) + 0.5) * side, y=y0 + (np.arange(ny) + 0.5) * side,
            zmin=np.log2(LOW), zmax=np.log2(HIGH), zmid=0, colorscale=COLOURMAP, showscale=number == 0,
            colorbar={"title": {"text": "kept / expected"}, "tickvals": np.log2(TICKS).tolist(),
                      "ticktext": [f"{t:g}" for t in TICKS], "len": 0.5},
            hovertemplate=f"x %{{x:.1f}} y %{{y:.1f}} ({unit})<br>kept / expected %{{customdata:.2f}}<extra></extra>"),
            **cell)
        figure.update_yaxes(scaleanchor=f"x{number + 1 if number else ''}", title_text=f"y ({unit})",
                            tickformat=",.0f", **cell)
        figure.update_xaxes(title_text=f"x ({unit})", tickformat=",.0f", **cell)
    strip = maps[0].grid.shape[1] / maps[0].grid.shape[0]
    figure.update_layout(height=int(rows * max(260, min(520, 900 / columns * strip + 120))),
                         margin={"l": 80, "r": 20, "t": 50, "b": 40}, plot_bgcolor="white")
    return figure


def density_png(maps: Sequence[DensityMap], labels: Sequence[str], unit: str, path: Path) -> Path:
    """The same maps as one PNG, a panel per output and one colour bar."""
    columns = columns_for(maps)
    rows = -(-len(maps) // columns)
    nx, ny = maps[0].grid.shape
    width = 12.0 if columns == 1 else 4.2 * columns
    panel_height = max(1.6, (width / columns - 1.2) * ny / nx + 1.0)  # the map at true proportions, plus labels
    figure = Figure(figsize=(width, panel_height * rows), layout="constrained")
    grid = figure.subplots(rows, columns, squeeze=False)
    image = None
    for axes, label, density in zip(grid.flat, labels, maps):
        image = axes.imshow(np.clip(density.ratio, LOW, HIGH), origin="lower", extent=density.extent,
                            cmap=COLOURMAP, norm=LogNorm(LOW, HIGH), interpolation="nearest")
        axes.set_title(title(label, density), fontsize="small")
        axes.set(xlabel=f"x ({unit})", ylabel=f"y ({unit})")
        axes.ticklabel_format(useOffset=False, style="plain")
        axes.xaxis.set_major_locator(MaxNLocator(4))
        axes.yaxis.set_major_locator(MaxNLocator(5))
        axes.tick_params(labelsize="x-small")
    for axes in grid.flat[len(maps):]:
        axes.set_axis_off()
    bar = figure.colorbar(image, ax=grid, shrink=0.8, label="kept / expected")
    bar.set_ticks(TICKS, labels=[f"{t:g}" for t in TICKS])
    bar.minorticks_off()
    figure.savefig(path, dpi=110)
    return path
