"""Simplifiers behind one interface (`simplify(tile, budget) -> Selection`), geometry and metrics."""
from model.selection import Selection, Simplifier, Tile
from model.registry import METHODS, get_simplifier

__all__ = ["METHODS", "Selection", "Simplifier", "Tile", "get_simplifier"]
