"""The bound on stopping (pipeline.engine.stop_guard): an armed guard ends a stuck process with its one line and
exit code; a cancelled one never fires. Run in fresh processes, since the guard ends its process."""
from __future__ import annotations

import subprocess
import sys

HANG_GUARD_S = 60  # a bound on the child, not a speed threshold

STUCK = """
import threading, time
from pipeline.engine.stop_guard import StopGuard
guard = StopGuard(grace_s=0.2)
guard.arm("pipeline: interrupted; finished work kept in /w: re-run the same command to resume", 130)
{then}
threading.Event().wait()  # a shutdown that never ends, as a deadlocked cluster close would
"""


def run_child(then: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", STUCK.format(then=then)], capture_output=True, text=True,
                          timeout=HANG_GUARD_S)


def test_an_armed_guard_ends_a_stuck_process_with_its_line_and_code():
    child = run_child("")
    assert child.returncode == 130
    assert child.stderr == "pipeline: interrupted; finished work kept in /w: re-run the same command to resume\n"


def test_a_cancelled_guard_never_fires():
    child = run_child("guard.cancel(); time.sleep(1.0); raise SystemExit(0)  # 5x its grace, then done")
    assert child.returncode == 0 and child.stderr == ""
