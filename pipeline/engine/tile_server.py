"""Imported by the forkserver that tile processes are forked from (pipeline.engine.processes), before it
serves: the tasks' code, once for every worker, then Python's own Ctrl-C handler.

The server shares the run's process group, so a Ctrl-C pressed while it imports (about 0.4 s, during the
run's reading) reached it too and printed its KeyboardInterrupt traceback under the run's one line. The run
therefore starts it with Ctrl-C ignored (an ignored signal stays ignored across exec). Once it serves, the
server ignores Ctrl-C itself; the handler is Python's own again before that, so whatever else it forks
later in the same process (Python 3.14 forks every new process from a forkserver by default) takes Ctrl-C
as usual, and a worker of ours ignores it in its own setup.

A SIGTERM to the process group (a scheduler's stop) killed the server too, and its workers with it (they die with
their parent): the pool broke under the run while it cancelled its tasks, and Python 3.11's pool then printed an
InvalidStateError traceback under the run's one line. The server ignores SIGTERM (it ends when the run's process
does, which decides how to stop); each process forked from it has SIGTERM's default again, so nothing else it
forks inherits the exemption, and a worker of ours ignores SIGTERM in its own setup.
"""
from __future__ import annotations

import os
import signal

from pipeline.io.lean_laspy import import_laspy_lean

import_laspy_lean()  # before the tasks' imports bring laspy in: tiles parse no CRS

import pipeline.engine.tasks  # noqa: E402, F401  (imported once here: each worker is forked with it)

signal.signal(signal.SIGINT, signal.default_int_handler)
signal.signal(signal.SIGTERM, signal.SIG_IGN)
os.register_at_fork(after_in_child=lambda: signal.signal(signal.SIGTERM, signal.SIG_DFL))
