"""The report's interactive before/after 3-D view: one plotly Scatter3d scene per cloud (the source, then each
output) of one region, every scene on the same axes and colour scale, cameras kept in step.

Coordinates are drawn relative to the region's lower-left corner: WebGL holds float32, which would round
projected coordinates (~5e5 m) to centimetres and make the points shimmer.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
import plotly.graph_objects as go
from plotly.subplots import make_subplots

from pipeline.apps.visual.report_region import Region, RegionSample

MARKER_SIZE = 1.6  # pixels: small enough that a dense facade still shows its windows
CAMERA = {"eye": {"x": 1.2, "y": -1.5, "z": 0.8}}  # oblique, from above one side: facades and poles show
# ASPRS LAS class codes 0-18: name and colour; any other code is OTHER_CLASS
CLASSES = (("never classified", "#9e9e9e"), ("unclassified", "#bdbdbd"), ("ground", "#a0522d"),
           ("low vegetation", "#b5e48c"), ("medium vegetation", "#52b788"), ("high vegetation", "#1b4332"),
           ("building", "#e63946"), ("low noise", "#6a040f"), ("key point", "#ffb703"), ("water", "#219ebc"),
           ("rail", "#6c757d"), ("road", "#343a40"), ("overlap", "#8d99ae"), ("wire guard", "#f72585"),
           ("wire", "#7209b7"), ("tower", "#fb8500"), ("wire connector", "#3a0ca3"), ("bridge", "#4361ee"),
           ("high noise", "#000000"))
OTHER_CLASS = "#d4a373"
# JavaScript run once the figure exists ({plot_id} is filled in by plotly): turning one scene turns them all
SYNC_CAMERAS = """
var plot = document.getElementById('{plot_id}');
var syncing = false;
plot.on('plotly_relayout', function (event) {
  var camera = null;
  Object.keys(event).forEach(function (key) { if (/^scene\\d*\\.camera$/.test(key)) { camera = event[key]; } });
  if (syncing || camera === null) { return; }
  var update = {};
  Object.keys(plot._fullLayout).forEach(function (key) {
    if (/^scene\\d*$/.test(key)) { update[key + '.camera'] = camera; }
  });
  syncing = true;
  Plotly.relayout(plot, update).then(function () { syncing = false; });
});
"""


@dataclass(frozen=True)
class ColourScale:
    """How values become colours, fixed from the source's region so every scene uses the same one."""

    color: str  # elevation | classification | rgb
    cmin: float
    cmax: float
    z_unit: str = ""

    @classmethod
    def of(cls, source: RegionSample, color: str, z_unit: str) -> "ColourScale":
        """Elevation: the source's 1st to 99th percentile of z; classification: codes 0..31; RGB: 8 or 16 bits."""
        if color == "elevation":
            low, high = np.percentile(source.values, [1, 99]) if len(source.values) else (0.0, 1.0)
            return cls(color, float(low), float(max(high, low + 1e-6)), z_unit)
        if color == "classification":
            return cls(color, -0.5, max(len(CLASSES) - 1, int(source.values.max(initial=0))) + 0.5)
        return cls(color, 0.0, 65535.0 if len(source.values) and source.values.max() > 255 else 255.0)

    def marker(self, values: np.ndarray, first: bool) -> dict[str, Any]:
        """A Scatter3d marker colouring `values`; the first scene carries the colour bar."""
        if self.color == "rgb":
            rgb = np.rint(np.asarray(values, dtype=np.float64) * 255 / self.cmax).astype(int)
            return {"size": MARKER_SIZE, "color": [f"rgb({r},{g},{b})" for r, g, b in rgb]}
        marker = {"size": MARKER_SIZE, "color": np.asarray(values, dtype=np.float32), "cmin": self.cmin,
                  "cmax": self.cmax, "showscale": first}
        if self.color == "elevation":
            return marker | {"colorscale": "Viridis",
                             "colorbar": {"title": {"text": f"z ({self.z_unit})"}, "len": 0.6}}
        codes = int(self.cmax + 0.5)  # colours 0 .. codes - 1, a step each
        colours = [CLASSES[c][1] if c < len(CLASSES) else OTHER_CLASS for c in range(codes)]
        steps = [[edge, colour] for code, colour in enumerate(colours) for edge in (code / codes, (code + 1) / codes)]
        present = [int(c) for c in np.unique(np.asarray(values, dtype=int))] if first else []
        names = [f"{c} {CLASSES[c][0]}" if c < len(CLASSES) else str(c) for c in present]
        return marker | {"colorscale": steps, "colorbar": {"title": {"text": "class"}, "tickvals": present,
                                                            "ticktext": names, "len": 0.6}}


def scene_layout(region: Region, z_range: tuple[float, float], unit: str, z_unit: str) -> dict[str, Any]:
    """Axes of every scene: the region's square and the source's z range, true proportions, titled in units."""
    z0, z1 = z_range
    height = max(z1 - z0, 1e-6)
    axis = {"showbackground": False}
    return {"xaxis": axis | {"range": [0, region.size], "title": {"text": f"x − {region.x0:,.1f} ({unit})"}},
            "yaxis": axis | {"range": [0, region.size], "title": {"text": f"y − {region.y0:,.1f} ({unit})"}},
            "zaxis": axis | {"range": [0, height], "title": {"text": f"z − {z0:,.1f} ({z_unit})"}},
            "aspectmode": "manual", "aspectratio": {"x": 1, "y": 1, "z": min(height / region.size, 1.0)},
            "camera": CAMERA}


def panel_title(label: str, sample: RegionSample) -> str:
    """`label: N points in the region`, and how many are shown when they were subsampled for the browser."""
    shown = "" if len(sample.xyz) == sample.total else f" (showing {len(sample.xyz):,})"
    return f"{label}: {sample.total:,} points{shown}"


def region_figure(panels: Sequence[tuple[str, RegionSample]], region: Region, scale: ColourScale, unit: str,
                  z_unit: str) -> go.Figure:
    """A grid of 3-D scenes (up to three a row), the source's panel first; x, y in `unit`, z in `z_unit`."""
    columns = min(3, len(panels))
    rows = -(-len(panels) // columns)
    figure = make_subplots(rows=rows, cols=columns, specs=[[{"type": "scene"}] * columns] * rows,
                           subplot_titles=[panel_title(label, sample) for label, sample in panels],
                           horizontal_spacing=0.02, vertical_spacing=0.06 / rows)
    source_z = panels[0][1].xyz[:, 2]
    z0 = float(source_z.min()) if len(source_z) else 0.0
    z1 = float(source_z.max()) if len(source_z) else 1.0
    for number, (label, sample) in enumerate(panels):
        local = sample.xyz - (region.x0, region.y0, z0)
        figure.add_trace(go.Scatter3d(x=local[:, 0].astype(np.float32), y=local[:, 1].astype(np.float32),
                                      z=local[:, 2].astype(np.float32), mode="markers", name=label,
                                      marker=scale.marker(sample.values, number == 0), hoverinfo="skip"),
                         row=number // columns + 1, col=number % columns + 1)
    layout = scene_layout(region, (z0, z1), unit, z_unit)
    figure.update_scenes(**layout)
    figure.update_layout(height=480 * rows, margin={"l": 0, "r": 0, "t": 40, "b": 0}, showlegend=False)
    return figure
