"""Progress off a terminal: a line every interval on stderr (JSON `progress` events with --log-json), for
run, eval, compare and batch; nothing with --quiet; bars only at a terminal."""
from __future__ import annotations

import io
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from pipeline.progress import Progress


def pipeline_cli(*args: str, interval: str = "0") -> subprocess.CompletedProcess:
    """The CLI in a child process, stderr a pipe (not a terminal), progress every `interval` seconds."""
    env = {**os.environ, "PIPELINE_PROGRESS_SECONDS": interval}
    return subprocess.run([sys.executable, "-m", "pipeline.apps.cli", *args], capture_output=True, text=True, env=env,
                          timeout=600)


def test_a_run_off_a_terminal_prints_progress_lines(tmp_path, street_scan):
    result = pipeline_cli("run", str(street_scan), "-r", "0.1", "-m", "fps", "-w", "1", "-o", str(tmp_path / "o.laz"))
    assert result.returncode == 0, result.stderr
    lines = [line for line in result.stderr.splitlines() if line.startswith("pipeline: ") and " of " in line]
    for phase in ("validate", "read and bucket", "survey tiles", "simplify", "resolve seams", "write o.laz"):
        assert any(line.startswith(f"pipeline: {phase}: ") for line in lines), (phase, result.stderr)
    assert any("points/s" in line for line in lines) and any("done in" in line for line in lines)
    assert "\r" not in result.stderr  # no bar redraws in a log file


def test_a_phase_of_long_tasks_says_it_is_alive_before_the_first_ends():
    """No step finishes for 2.6 s with a 1 s interval: the heartbeat still writes lines, then the final one,
    which says the phase stopped short (as a failed or interrupted run's does), not that it was done."""
    stream = io.StringIO()
    with Progress("lines", interval=1.0, stream=stream).phase("simplify", 3) as phase:
        time.sleep(2.6)
        phase.update(1, 1_000)
    lines = stream.getvalue().splitlines()
    assert sum(line.startswith("pipeline: simplify: 0 of 3 tasks") for line in lines) >= 2, lines
    assert lines[-1].startswith("pipeline: simplify: 1 of 3 tasks") and "stopped after 3 s" in lines[-1]


def test_quiet_and_a_long_interval_print_nothing(tmp_path, street_scan):
    quiet = pipeline_cli("run", str(street_scan), "-r", "0.1", "-m", "random", "-w", "1", "-q", "-o",
                         str(tmp_path / "a.laz"))
    slow = pipeline_cli("run", str(street_scan), "-r", "0.1", "-m", "random", "-w", "1", "-o", str(tmp_path / "b.laz"),
                        interval="3600")
    assert quiet.returncode == slow.returncode == 0
    assert quiet.stderr == "" and quiet.stdout == ""
    assert " of " not in slow.stderr  # no phase outlived the interval


def test_log_json_emits_progress_events(tmp_path, street_scan):
    result = pipeline_cli("run", str(street_scan), "-r", "0.1", "-m", "fps", "-w", "1", "--log-json", "-o",
                          str(tmp_path / "o.laz"))
    events = [json.loads(line) for line in result.stdout.splitlines()]
    progress = [e for e in events if e["event"] == "progress"]
    assert progress and events[-1]["event"] == "done"
    assert {"phase", "done", "total", "points_per_s", "eta_s"} <= set(progress[0])
    assert {e["phase"] for e in progress} >= {"read and bucket", "simplify"}


@pytest.mark.parametrize("command", ["eval", "batch", "compare"])
def test_eval_batch_and_compare_show_progress(tmp_path, street_scan, command):
    if command == "eval":
        args = ("eval", str(street_scan), str(street_scan), "--sample", "20000")
        expected = ("read street.laz", "score candidates")
    elif command == "batch":
        (tmp_path / "scans").mkdir()
        (tmp_path / "scans" / "street.laz").write_bytes(Path(street_scan).read_bytes())
        args = ("batch", str(tmp_path / "scans"), "--out-dir", str(tmp_path / "out"), "-r", "0.1", "-m", "random",
                "-w", "1")
        expected = ("batch", "read and bucket")
    else:
        args = ("compare", str(street_scan), "--ratios", "0.1", "--methods", "random,fps", "--out-dir",
                str(tmp_path / "cmp"), "-w", "1", "--sample", "20000")
        expected = ("read street.laz", "compare: run and score")
    result = pipeline_cli(*args)
    assert result.returncode == 0, result.stderr
    for phase in expected:
        assert f"pipeline: {phase}: " in result.stderr, (phase, result.stderr)
