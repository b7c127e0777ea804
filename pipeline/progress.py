"""Progress wherever work is long: bars at a terminal; elsewhere (cron, nohup, `2>log`, Slurm) one line
every `interval` seconds, or JSON `progress` events with `--log-json`; nothing with `--quiet`.

Every phase reports tasks (or tiles, runs, files) done of a total and, where it knows them, points per
second; the ETA comes from the share of tasks done.
"""
from __future__ import annotations

import json
import os
import sys
import threading
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from typing import Any, Callable, Iterable, Iterator, TextIO, TypeVar


INTERVAL_ENV = "PIPELINE_PROGRESS_SECONDS"  # seconds between progress lines off a terminal
DEFAULT_INTERVAL = 10.0
HEARTBEAT_MIN = 1.0  # seconds: shorter intervals (tests) print on finished steps only
T = TypeVar("T")


@dataclass
class Progress:
    """How progress is shown: `mode` is "bar", "lines", "json" or "off"; lines and JSON events go to
    `stream` at most every `interval` seconds per phase."""

    mode: str = "off"
    interval: float = field(default_factory=lambda: float(os.environ.get(INTERVAL_ENV, DEFAULT_INTERVAL)))
    stream: TextIO | None = None

    @classmethod
    def for_terminal(cls, quiet: bool = False, log_json: bool = False) -> "Progress":
        """Bars when stderr is a terminal, lines on stderr when it is not, JSON on stdout with log_json."""
        if log_json:
            return cls("json")
        if quiet:
            return cls("off")
        return cls("bar" if sys.stderr.isatty() else "lines")

    def phase(self, desc: str, total: int, unit: str = "task") -> "Phase":
        """A phase of `total` steps: update it as steps finish, close it at the end (or use `with`)."""
        return Phase(self, desc, total, unit)

    def emit(self, phase: "Phase", final: bool = False) -> None:
        """Write one progress line or JSON event about `phase`."""
        elapsed = time.perf_counter() - phase.started
        rate = phase.points / elapsed if phase.points and elapsed > 0 else None
        eta = elapsed * (phase.total - phase.done) / phase.done if phase.done and not final else None
        if self.mode == "json":
            event = {"time": datetime.now(timezone.utc).isoformat(timespec="milliseconds"), "event": "progress",
                     "phase": phase.desc, "done": phase.done, "total": phase.total, "unit": phase.unit,
                     "points": phase.points, "points_per_s": None if rate is None else round(rate),
                     "eta_s": None if eta is None else round(eta, 1), "elapsed_s": round(elapsed, 1)}
            print(json.dumps(event), file=self.stream or sys.stdout, flush=True)
            return
        share = f" ({100 * phase.done / phase.total:.0f} %)" if phase.total else ""
        speed = f", {rate:,.0f} points/s" if rate is not None else ""
        ended = "done in" if phase.done >= phase.total else "stopped after"  # a failed or interrupted phase
        when = f", {ended} {elapsed:.0f} s" if final else (f", about {eta:.0f} s left" if eta is not None else "")
        print(f"pipeline: {phase.desc}: {phase.done:,} of {phase.total:,} {phase.unit}s{share}{speed}{when}",
              file=self.stream or sys.stderr, flush=True)


class Phase:
    """One phase's count of steps and points, shown as its Progress says. Off a terminal a heartbeat
    thread writes the line when no step finished for an interval, so a phase of a few long tasks is not
    silent until the first ends (intervals under HEARTBEAT_MIN seconds rely on the steps alone)."""

    def __init__(self, progress: Progress, desc: str, total: int, unit: str) -> None:
        self.progress, self.desc, self.total, self.unit = progress, desc, total, unit
        self.done = self.points = 0
        self.started = self.last = time.perf_counter()
        self.bar = progress_bar(total, desc, unit) if progress.mode == "bar" else None
        self._lock, self._stopped = threading.Lock(), threading.Event()
        if progress.mode in ("lines", "json") and progress.interval >= HEARTBEAT_MIN:
            threading.Thread(target=self._beat, daemon=True).start()

    def _beat(self) -> None:
        """Emit a line every interval in which no step did."""
        while not self._stopped.wait(self.progress.interval / 4):
            self._emit_if_due()

    def _emit_if_due(self) -> None:
        with self._lock:
            if time.perf_counter() - self.last >= self.progress.interval and not self._stopped.is_set():
                self.last = time.perf_counter()
                self.progress.emit(self)

    def update(self, steps: int = 1, points: int = 0) -> None:
        """Count finished steps and the points they handled."""
        self.done += steps
        self.points += points
        if self.bar is not None:
            elapsed = time.perf_counter() - self.started
            if self.points and elapsed > 0:
                self.bar.set_postfix_str(f"{self.points / elapsed:,.0f} points/s")
            self.bar.update(steps)
        elif self.progress.mode in ("lines", "json"):
            self._emit_if_due()

    def close(self) -> None:
        """End the phase: a last line when it ran long enough to have shown progress."""
        if self.bar is not None:
            self.bar.close()
        with self._lock:
            self._stopped.set()
            if self.progress.mode in ("lines", "json") and self.last > self.started:
                self.progress.emit(self, final=True)

    def __enter__(self) -> "Phase":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def progress_bar(total: int, desc: str, unit: str) -> Any:
    """A terminal's progress bar for a phase (tqdm, imported here: a run off a terminal never loads it)."""
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit=unit, leave=False)


def counted(items: Iterable[T], phase: Phase, points: Callable[[T], int] = lambda item: 0) -> Iterator[T]:
    """Yield `items`, counting each as a finished step of `phase` once the consumer asks for the next."""
    for item in items:
        yield item
        phase.update(1, points(item))
