"""Workers map a tile's arrays whole (pipeline.engine.allocator): glibc then gives their memory back when they
are freed, instead of serving the next ones from a heap it fragments (a worker's memory would grow
with the tiles it has run). Checked through glibc's own count of mapped bytes, in fresh processes."""
from __future__ import annotations

import ctypes
import subprocess
import sys

import pytest

from pipeline.engine.dask_cluster import local_cluster

PROBE = """
import ctypes, numpy as np
class MallInfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                                      "fsmblks", "uordblks", "fordblks", "keepcost")]
libc = ctypes.CDLL("libc.so.6")
libc.mallinfo2.restype = MallInfo2
def mapped_mib_of_new_array(mib=8):
    del_me = np.ones(20 << 20, np.uint8)  # freed: glibc's own rule then serves arrays under 20 MiB from its heap
    del del_me
    before = libc.mallinfo2().hblkhd
    kept = np.ones(mib << 20, np.uint8)
    return (libc.mallinfo2().hblkhd - before) >> 20
"""


def glibc_with_mallinfo2() -> bool:
    try:
        return hasattr(ctypes.CDLL("libc.so.6"), "mallinfo2")
    except OSError:
        return False


pytestmark = pytest.mark.skipif(not glibc_with_mallinfo2(), reason="needs glibc 2.33 or later (mallinfo2)")


def mapped_mib(setup: str, mib: int = 8) -> int:
    """MiB of a new `mib` MiB array that glibc mapped on its own, in a fresh process after `setup`."""
    code = f"{setup}\n{PROBE}\nprint(mapped_mib_of_new_array({mib}))"
    return int(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout)


def test_large_arrays_are_mapped_whole_after_the_setting():
    assert mapped_mib("") == 0  # glibc's default: the array comes from the heap
    assert mapped_mib("from pipeline.engine.allocator import map_large_arrays; assert map_large_arrays()") == 8


def test_a_survey_batch_table_stays_on_the_heap():
    """A 2 MiB array (an 8k-row neighbour gather is 1-3 MiB, remade every batch) is reused from the heap, not
    mapped afresh and faulted in page by page each time (pipeline.engine.allocator: the 4 MiB threshold)."""
    assert mapped_mib("from pipeline.engine.allocator import map_large_arrays; assert map_large_arrays()", 2) == 0


def worker_probe() -> int:
    namespace: dict = {}
    exec(PROBE, namespace)
    return namespace["mapped_mib_of_new_array"]()


def test_local_cluster_workers_map_large_arrays():
    with local_cluster(1, "1GB") as client:
        assert client.submit(worker_probe, pure=False).result() == 8
