"""Peak resident memory of a command's whole process tree (Dask workers included), sampled by psutil."""
from __future__ import annotations

import os
import subprocess
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import psutil

SAMPLE_SECONDS = 0.05
FOLDER_SAMPLE_SECONDS = 2.0  # walking a work folder of thousands of files costs more than a process tree


@dataclass(frozen=True)
class Measured:
    """Wall time, peak summed RSS of the tree, exit code and output of one command (and, if a folder was
    watched, the most bytes its files held at once, sampled every FOLDER_SAMPLE_SECONDS)."""

    seconds: float
    peak_rss_bytes: int
    returncode: int
    stdout: str
    stderr: str
    peak_folder_bytes: int = 0


def tree_rss(process: psutil.Process) -> int:
    """RSS of a process and all its descendants, in bytes (processes that vanish mid-read count 0)."""
    total = 0
    for member in [process, *process.children(recursive=True)]:
        try:
            total += member.memory_info().rss
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            pass
    return total


def folder_bytes(folder: Path) -> int:
    """Bytes of the files under a folder (files that vanish mid-walk count 0)."""
    total = 0
    for root, _, names in os.walk(folder):
        for name in names:
            try:
                total += os.stat(os.path.join(root, name)).st_size
            except OSError:
                pass
    return total


def measure(command: Sequence[str], watch_folder: Path | None = None) -> Measured:
    """Run a command to completion, sampling its tree's RSS every 50 ms (and `watch_folder`'s size)."""
    started = time.perf_counter()
    child = subprocess.Popen(list(command), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    watched = psutil.Process(child.pid)
    peak, folder_peak = [0], [0]
    done = threading.Event()

    def sample() -> None:
        while not done.is_set():
            try:
                peak[0] = max(peak[0], tree_rss(watched))
            except psutil.NoSuchProcess:
                return
            time.sleep(SAMPLE_SECONDS)

    def sample_folder() -> None:
        while watch_folder is not None and not done.wait(FOLDER_SAMPLE_SECONDS):
            folder_peak[0] = max(folder_peak[0], folder_bytes(watch_folder))

    samplers = [threading.Thread(target=sample, daemon=True), threading.Thread(target=sample_folder, daemon=True)]
    for sampler in samplers:
        sampler.start()
    stdout, stderr = child.communicate()
    seconds = time.perf_counter() - started
    done.set()
    for sampler in samplers:
        sampler.join()
    return Measured(seconds, peak[0], child.returncode, stdout, stderr, folder_peak[0])
