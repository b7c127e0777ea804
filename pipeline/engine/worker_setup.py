"""Imported by every Dask worker process as it starts (a preload), and by the forkserver that `fps`'s picking
processes are forked from (pipeline.engine.processes): the tasks' code, and signals left to the run.

Ctrl-C and SIGTERM reach the whole process group, workers included. A worker that died of them would
print a KeyboardInterrupt traceback (or leave its scratch folder behind) and be restarted by its nanny;
instead workers ignore both (a forked worker inherits that), and the run's own process, which gets them
too, shuts the cluster or the pool down cleanly. A worker still ends with that process: Dask closes it
when its parent goes away, and a picking process's queue ends with it.
"""
from __future__ import annotations

import signal
import threading

import pipeline.engine.tasks  # noqa: F401  (imported as the worker starts, not on its first task)
from pipeline.engine.allocator import map_large_arrays

map_large_arrays()  # a forked worker keeps its server's setting (a Dask worker's plugin sets it too, remote ones included)
if threading.current_thread() is threading.main_thread():
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
