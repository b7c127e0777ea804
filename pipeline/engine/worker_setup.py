"""Imported by every Dask worker process as it starts (a preload): the tasks' code, and signals left to the run.

Ctrl-C and SIGTERM reach the whole process group, workers included. A worker that died of them would
print a KeyboardInterrupt traceback (or leave its scratch folder behind) and be restarted by its nanny;
instead workers ignore both, and the run's own process, which gets them too, shuts the cluster down
cleanly. A worker still ends with that process: Dask closes it when its parent goes away.
"""
from __future__ import annotations

import signal
import threading

import pipeline.engine.tasks  # noqa: F401  (imported as the worker starts, not on its first task)

if threading.current_thread() is threading.main_thread():
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
