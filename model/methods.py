"""Simplifiers as values: each a frozen dataclass holding its parameters (picklable, hashable, compared by
value), called as `method(tile, budget) -> Selection`, and saying what a run must know of it: whether it
reads a tile's halo, spaces points evenly, or fills by a loss the run surveys first.

A parameter is a dataclass field with its default; model.registry names the methods. A run's work folder
and an output's provenance read the fields, so a parameter added here needs no other change.
"""
from __future__ import annotations

import zipfile
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from model.baselines import VOXEL_COUNT_SLACK, fps_simplify, random_simplify, tcp_simplify, voxel_simplify
from model.detail import DESCRIPTORS, load_detail_weights, predicted_fill_loss
from model.learning import DETAIL_WEIGHTS, PAPER_WEIGHTS
from model.selection import FillLoss, Selection, Tile
from model.stratified import CHAMFER_BOUND, COVER_SPACINGS, measured_loss, no_loss, stratified_selection


@dataclass(frozen=True)
class Method:
    """A simplifier with its parameters. Class flags tell the run how to feed it."""

    reads_halo: ClassVar[bool] = True        # False: picks from the core alone, so a run loads no halo for it
    picks_read_halo: ClassVar[bool] = True   # False: only its survey reads the halo; its picks read the core alone
    spaces_evenly: ClassVar[bool] = False    # True: tile budgets follow covered volume, not point counts
    light_on_gil: ClassVar[bool] = False     # True: its work runs in compiled code (numpy, fpsample), so threads of
                                             # one process beat a cluster's start on bigger scans (measured; fpsample
                                             # itself keeps the GIL: its picks go one thread at a time)
    tile_processes_from: ClassVar[int | None] = None  # scan points from which a run on threads of one process gives
                                                      # its tile work (survey and picks) to worker processes, where that
                                                      # work holds the GIL a fair share (fpsample throughout, the hole
                                                      # cover's loop, numpy on small tiles): pipeline.engine.processes.
                                                      # None: never (the start costs more than the GIL takes)
    sees_tile_extent: ClassVar[bool] = False  # True: its picks depend on how far a tile reaches, so the run does not
                                              # merge sparse tiles for it (pipeline.config.RunConfig.merge_limit)

    def __call__(self, tile: Tile, budget: int) -> Selection:
        """`budget` core points of `tile` (fewer only if it has fewer), most important first."""
        raise NotImplementedError

    def on_mesh(self, tile: Tile, budget: int, faces: np.ndarray) -> Selection:
        """The same for a mesh's vertices as one tile; (f, 3) `faces` for a method that can use them."""
        return self(tile, budget)

    def parameters(self) -> dict[str, Any]:
        """Every parameter and its value, JSON-able (paths as strings)."""
        return {f.name: str(v) if isinstance(v := getattr(self, f.name), Path) else v for f in fields(self)}

    def __post_init__(self) -> None:
        """A `weights` field (a file of trained weights) becomes a checked Path once, when the method is made,
        so equal settings give equal methods."""
        if isinstance(getattr(self, "weights", None), (str, Path)):
            object.__setattr__(self, "weights", checked_weights(getattr(self, "weights")))
            self.check_weights(getattr(self, "weights"))

    def check_weights(self, path: Path) -> None:
        """Raise ValueError if the file at `path` is not the kind of weights this method reads (a method with a
        `weights` field says which), so a wrong file fails before any work, not in the first tile."""

    def trained_weights(self) -> Path | None:
        """The file of trained weights the method runs on, its `weights` field if it has one (an output's
        provenance records its digest)."""
        return getattr(self, "weights", None)

    def keeps_positions(self) -> bool:
        """Whether the selection's xyz are the picked points' own (False: the method moves them)."""
        return True


@dataclass(frozen=True)
class Fps(Method):
    """3-D farthest point sampling over a tile's core (model.baselines.fps_simplify)."""

    reads_halo: ClassVar[bool] = False
    spaces_evenly: ClassVar[bool] = True
    light_on_gil: ClassVar[bool] = True
    tile_processes_from: ClassVar[int | None] = 1_000_000  # fpsample alone holds the GIL: 519-698k gained nothing

    def __call__(self, tile: Tile, budget: int) -> Selection:
        return fps_simplify(tile, budget)


@dataclass(frozen=True)
class Voxel(Method):
    """The real point nearest each voxel centre, the cell searched so the voxels number at most `slack`
    over the budget (the extra ones trimmed last in a spread-out order)."""

    slack: float = VOXEL_COUNT_SLACK
    reads_halo: ClassVar[bool] = False
    spaces_evenly: ClassVar[bool] = True
    light_on_gil: ClassVar[bool] = True
    tile_processes_from: ClassVar[int | None] = 2_000_000  # its many numpy calls per tile contend for the GIL on
    # threads: bcts (2.8M) simplified 1.78 -> 1.35 s in processes, a 10M street 4 % faster; a tie at 2M, and at 1M
    # the forkserver's start (beside the reading) cost 0.15 s more than the processes saved

    def __post_init__(self) -> None:
        super().__post_init__()
        if not 0 <= self.slack <= 1:
            raise ValueError(f"parameter 'slack' must be a share in [0, 1], got {self.slack!r}")

    def __call__(self, tile: Tile, budget: int) -> Selection:
        return voxel_simplify(tile, budget, self.slack)


@dataclass(frozen=True)
class Random(Method):
    """A seeded uniform sample of the core."""

    reads_halo: ClassVar[bool] = False
    light_on_gil: ClassVar[bool] = True

    def __call__(self, tile: Tile, budget: int) -> Selection:
        return random_simplify(tile, budget)


@dataclass(frozen=True)
class TopCurvature(Method):
    """The paper's TCP baseline: the points of highest curvature."""

    def __call__(self, tile: Tile, budget: int) -> Selection:
        return tcp_simplify(tile, budget)


@dataclass(frozen=True)
class Fill(Method):
    """The stratified fill and hole cover (model.stratified), each point weighted by its fill loss; a run
    surveys every tile's loss first, so weights and the hole radius are set for the whole scan. A hole
    is a point farther than `cover_spacings` typical output spacings from every pick; a run narrows that
    radius until its estimate of the output's Chamfer distance is at most `chamfer_bound` times an even
    thinning's (model.chamfer_bound), as the budgets at `detail` 1 would leave it, whatever the weights (a tile
    simplified on its own, as a mesh's vertices are, estimates it from its own trial fill)."""

    cover_spacings: float = COVER_SPACINGS
    chamfer_bound: float = CHAMFER_BOUND
    picks_read_halo: ClassVar[bool] = False  # a run surveys its loss (the halo as neighbours); the fill and cover: core
    tile_processes_from: ClassVar[int | None] = 300_000  # the survey and hole cover: a tie at 277k, 0.05-0.16 s
                                                         # gained from 410k, 0.06-0.1 s lost at 110-155k (2 cores)

    def __post_init__(self) -> None:
        super().__post_init__()
        for name in ("cover_spacings", "chamfer_bound"):
            if not (np.isfinite(getattr(self, name)) and getattr(self, name) > 0):
                raise ValueError(f"parameter {name!r} must be a positive number, got {getattr(self, name)!r}")

    def fill_loss(self, tile: Tile, budget: int) -> FillLoss:
        """Each point's fill loss (none here: every point weighs the same)."""
        return no_loss(tile, budget)

    def loss_strength(self) -> float:
        """How strongly the keep weights follow the loss: weights 1 + strength x loss / the scan's mean loss."""
        return 1.0

    def __call__(self, tile: Tile, budget: int) -> Selection:
        return stratified_selection(tile, budget, self.fill_loss, self.cover_spacings, self.loss_strength(),
                                    self.chamfer_bound)


@dataclass(frozen=True)
class DetailFill(Fill):
    """A fill weighted by a curvature loss, `detail` times as strongly as the default: keep weights
    1 + detail x loss / the scan's mean loss. Below 1 the output's density follows the scan's more evenly
    (Chamfer and the 99th-percentile distance fall); above 1 detail keeps more (the curvature error falls):
    the trade bench/results/frontier.md sweeps. 0 gives every point the same chance, as `stratified` does;
    the hole radius and each tile's hole count are the default's at any value (measured at strength 1)."""

    detail: float = 1.0

    def __post_init__(self) -> None:
        super().__post_init__()
        if not (np.isfinite(self.detail) and self.detail >= 0):
            raise ValueError(f"parameter 'detail' must be a number >= 0, got {self.detail!r}")

    def loss_strength(self) -> float:
        return self.detail


@dataclass(frozen=True)
class MeasuredDetail(DetailFill):
    """The fill weighted by the curvature loss measured on the tile (no network)."""

    def fill_loss(self, tile: Tile, budget: int) -> FillLoss:
        return measured_loss(tile, budget)


@dataclass(frozen=True)
class Learned(DetailFill):
    """The default: the fill weighted by the curvature loss the TOSCA-trained predictor expects at each
    point (model/detail.py, run in numpy from `weights`: no torch in its workers)."""

    weights: Path = DETAIL_WEIGHTS

    def fill_loss(self, tile: Tile, budget: int) -> FillLoss:
        return predicted_fill_loss(tile, budget, self.weights)

    def check_weights(self, path: Path) -> None:
        try:  # one prediction: the arrays' names and shapes as the predictor reads them
            load_detail_weights(path).predict(np.zeros((1, DESCRIPTORS), dtype=np.float32))
        except (OSError, ValueError, KeyError, zipfile.BadZipFile) as exc:
            raise ValueError(f"parameter 'weights': {path} is not the detail predictor's weights (an .npz written "
                             f"by `pipeline train-detail`): {exc}") from None


@dataclass(frozen=True)
class Paper(Method):
    """The paper's network from `weights`: latent-FPS picks at their measured positions, or with
    `refine` moved by its attention refinement (CD 1.5-3.2x higher for the same CE on the TOSCA test
    split; see the model card). On a mesh its GNN aggregates over the mesh adjacency, as the paper does."""

    weights: Path = PAPER_WEIGHTS
    refine: bool = False
    sees_tile_extent: ClassVar[bool] = True  # the network sees a tile in its unit ball: merged, larger tiles cost it
                                             # CD +24 % and CE +11 % on autzen at 0.1, CE +12 % on the extra-bytes file

    def __call__(self, tile: Tile, budget: int, graph: np.ndarray | None = None) -> Selection:
        from model.learned import learned_simplify  # torch: imported by this method only

        return learned_simplify(tile, budget, self.weights, graph=graph, refine=self.refine)

    def on_mesh(self, tile: Tile, budget: int, faces: np.ndarray) -> Selection:
        from model.learning.network import GRAPH_NEIGHBOURS
        from model.meshes import mesh_graph

        return self(tile, budget, mesh_graph(tile.xyz, faces, GRAPH_NEIGHBOURS))

    def keeps_positions(self) -> bool:
        return not self.refine

    def check_weights(self, path: Path) -> None:
        if zipfile.is_zipfile(path):
            with zipfile.ZipFile(path) as archive:
                if any(name.endswith("data.pkl") for name in archive.namelist()):
                    return
        raise ValueError(f"parameter 'weights': {path} is not a torch checkpoint of the paper's network (a .pt "
                         "written by `pipeline train`)")


def checked_weights(path: Path | str) -> Path:
    """A method's `weights` as a Path, which must name a file (checked when the method is made, not in its
    first tile; a string becomes a Path, so equal settings make equal methods)."""
    if not Path(path).is_file():
        raise ValueError(f"parameter 'weights': no such file {str(path)!r}")
    return Path(path)
