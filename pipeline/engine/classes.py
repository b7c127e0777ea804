"""Class-aware thinning: which points a run keeps whole (`--keep-class 6,14,15`, or every class but those of
`--thin-class 2`) and which it thins to the ratio."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.config import RunConfig

CLASS_BITS = 0x1F  # formats 0-5 pack the class in five bits beside synthetic/key-point/withheld


@dataclass(frozen=True)
class ClassRule:
    """Keep the points of `keep` whole, or, with `thin` given, keep whole every point not of `thin`."""

    keep: tuple[int, ...] = ()
    thin: tuple[int, ...] = ()

    @classmethod
    def of(cls, config: RunConfig) -> "ClassRule":
        """The rule a run's settings give (inactive when neither option is set)."""
        return cls(tuple(config.keep_classes), tuple(config.thin_classes))

    @property
    def active(self) -> bool:
        """Whether any point may be kept whole."""
        return bool(self.keep or self.thin)

    def protected(self, records: np.ndarray) -> np.ndarray:
        """(n,) bool: which raw records are kept whole."""
        if not self.active:
            return np.zeros(len(records), dtype=bool)
        codes = classification(records)
        return np.isin(codes, self.keep) if self.keep else ~np.isin(codes, self.thin)

    def describe(self) -> str:
        """The rule in words for a summary: 'classes 6, 14 kept whole' or 'only classes 2 thinned'."""
        if self.keep:
            return f"class{'es' if len(self.keep) > 1 else ''} {', '.join(map(str, self.keep))} kept whole"
        return f"only class{'es' if len(self.thin) > 1 else ''} {', '.join(map(str, self.thin))} thinned"


def classification(records: np.ndarray) -> np.ndarray:
    """(n,) uint8 classification codes of raw LAS records: a byte of its own in formats 6-10, the low five
    bits of `raw_classification` in formats 0-5."""
    if "classification" in records.dtype.names:
        return np.asarray(records["classification"], dtype=np.uint8)
    return np.asarray(records["raw_classification"], dtype=np.uint8) & CLASS_BITS


def class_histogram(records: np.ndarray) -> np.ndarray:
    """(256,) int64 points per classification code."""
    return np.bincount(classification(records), minlength=256).astype(np.int64)
