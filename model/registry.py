"""Method names to simplifier callables: the one switch behind `--method`."""
from __future__ import annotations

from model.baselines import fps_simplify, random_simplify, tcp_simplify, voxel_simplify
from model.selection import FillLoss, Selection, Simplifier, Tile
from model.stratified import LossOf, measured_detail_simplify, measured_loss, no_loss, stratified_simplify


def learned_simplify(tile: Tile, budget: int) -> Selection:
    """The default: the stratified fill weighted by the curvature loss the TOSCA-trained predictor expects
    (model/detail.py), run in numpy: no torch in its workers."""
    from model.detail import learned_detail_simplify

    return learned_detail_simplify(tile, budget)


def learned_loss(tile: Tile, budget: int) -> FillLoss:
    """The default's fill weights: the predicted curvature loss (model/detail.py)."""
    from model.detail import predicted_fill_loss

    return predicted_fill_loss(tile, budget)


def paper_simplify(tile: Tile, budget: int) -> Selection:
    """The paper's network: latent-FPS picks at their measured positions (model/learned.py)."""
    from model.learned import learned_simplify as simplify

    return simplify(tile, budget)


def paper_refined_simplify(tile: Tile, budget: int) -> Selection:
    """The paper's whole model: the same picks, moved by the attention refinement (CD 1.5-3.2x higher on
    the TOSCA test split for the same CE; see the model card)."""
    from model.learned import learned_simplify as simplify

    return simplify(tile, budget, refine=True)


_SIMPLIFIERS: dict[str, Simplifier] = {
    "fps": fps_simplify,
    "voxel": voxel_simplify,
    "random": random_simplify,
    "tcp": tcp_simplify,
    "stratified": stratified_simplify,
    "stratified-detail": measured_detail_simplify,
    "learned": learned_simplify,
    "paper": paper_simplify,
    "paper-refined": paper_refined_simplify,
}
PAPER = ("paper", "paper-refined")  # the paper's network: mesh mode gives its GNN the mesh adjacency
EVEN_SPACING = ("fps", "voxel")  # methods that space points evenly: tile budgets follow covered volume, not counts
CORE_ONLY = ("fps", "voxel", "random")  # methods that never look at a tile's halo: their tiles load their core only
FILL_LOSSES: dict[str, LossOf] = {"stratified": no_loss, "stratified-detail": measured_loss, "learned": learned_loss}
"""Stratified methods and their fill weights: a run surveys every tile first, so weights, cover radius
and tile budgets are set for the whole scan (model.selection.FillContext), as one pass over it would."""
METHODS = tuple(_SIMPLIFIERS)


def get_simplifier(method: str) -> Simplifier:
    """The simplifier registered under `method` (KeyError names the known ones)."""
    try:
        return _SIMPLIFIERS[method]
    except KeyError:
        raise KeyError(f"unknown method {method!r}; known: {', '.join(METHODS)}") from None
