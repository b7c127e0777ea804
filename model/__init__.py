"""Simplifiers behind one interface (`method(tile, budget) -> Selection`, each a frozen dataclass holding its
parameters: model.methods), geometry and metrics."""
from model.methods import Method
from model.registry import METHODS, get_simplifier
from model.selection import Selection, Tile

__all__ = ["METHODS", "Method", "Selection", "Tile", "get_simplifier"]
