"""How a worker's C allocator holds memory: arrays of a tile's size mapped and unmapped whole, so a
worker's resident memory stays near its largest tile's working set however many tiles it has run.

Why: glibc serves an allocation from its heap below a threshold it raises at run time (up to 32 MiB,
after the first large array is freed); a tile's arrays (a 200k-point tile's neighbour table is 25 MiB)
then land in heaps that smaller, longer-lived objects pin, and fragment them. Measured on simulated
streets (bench/results/scale.md), a worker grew from about 250 MiB to 320-365 MiB over 62-300 tiles;
malloc_trim after every task did not help (the growth is the peak within a task, not memory left
over). A fixed threshold keeps them in mappings of their own. At 4 MiB, not 1: the survey's per-batch
tables (8k-row neighbour gathers of 1-3 MiB, remade for every batch) then come from the heap, reused,
where at 1 MiB each was a fresh mapping faulted in page by page (a 6M street's run took 1.95M minor
faults against 104k on threads). A 20M street on 2 workers, two runs each: simplify phase 62.9 / 67.5 s
at 1 MiB, 54.0 / 52.5 at 4, 58.2 / 57.2 at 8, 53.8 / 56.2 with glibc's own rule; peak RSS of the whole
tree 446 / 451, 466 / 457, 478 / 461, 482 / 496 MiB. The 16 MiB trim threshold keeps the heap's top from
being given back and faulted in again for every small array (a 128 KiB one made bcts 7 % slower; Dask's
64 KiB one, 1.5x). No effect where the C library is not glibc.
"""
from __future__ import annotations

import ctypes
import ctypes.util

M_TRIM_THRESHOLD = -1  # glibc's mallopt parameter numbers (malloc.h)
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_BYTES = 4 << 20  # arrays this large get their own mapping, returned to the system when freed
TRIM_THRESHOLD_BYTES = 16 << 20  # free memory at the heap's top kept for reuse, up to this much


def map_large_arrays() -> bool:
    """Fix glibc's mmap and trim thresholds in this process (see module doc); False where there is no glibc."""
    try:
        mallopt = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").mallopt
    except (OSError, AttributeError):
        return False
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) and bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES))
