"""The package's version, set here alone: pyproject.toml reads it, and outputs and work folders record it (a
module of its own, below every layer that records it, so none has to ask importlib.metadata at run time)."""

__version__ = "0.3.15"
