"""The trained parts: the paper's network and its losses and training, the detail predictor's network and
training, and the weights they produced (`weights/`, with its model card). Only training and the `paper`
method import torch; the default method runs the detail predictor from numpy weights."""
from pathlib import Path

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
PAPER_WEIGHTS = WEIGHTS_DIR / "tosca.pt"    # the paper's network (`paper`, `paper-refined`)
DETAIL_WEIGHTS = WEIGHTS_DIR / "detail.npz"  # the default's predictor, exported from detail.pt (the training record)
