"""Real faults on real processes: a Dask worker killed mid-run, the whole job SIGKILLed and re-run."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import laspy
import numpy as np
import psutil
import pytest

from tests.conftest import simulated_street

SETTINGS = ["--ratio", "0.1", "--method", "learned", "--tile-size", "8", "--workers", "2", "--seed", "5"]
ON_A_CLUSTER = Path(__file__).with_name("on_a_cluster.toml")  # a scan this small would otherwise run in process


@pytest.fixture(scope="module")
def scan(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return simulated_street(tmp_path_factory, "faults", 120_000, 9)


@pytest.fixture(scope="module")
def clean_output(scan: Path, tmp_path_factory: pytest.TempPathFactory) -> np.ndarray:
    out = tmp_path_factory.mktemp("clean") / "clean.laz"
    subprocess.run(command(scan, out), check=True, capture_output=True)
    return laspy.read(out).points.array


def command(scan: Path, out: Path) -> list[str]:
    return [sys.executable, "-m", "pipeline.apps.cli", "run", str(scan), "-o", str(out), *SETTINGS, "--config",
            str(ON_A_CLUSTER)]


def finished_tiles(out: Path) -> int:
    return sum(1 for _ in out.parent.glob(f".{out.name}.work-*/tile-*.npz"))


def wait_for_tiles(job: subprocess.Popen, out: Path, count: int) -> None:
    """Block until `count` tiles are finished; fail if the job ends first (then no fault was injected)."""
    while finished_tiles(out) < count:
        assert job.poll() is None, "the run ended before the fault could be injected"
        time.sleep(0.05)


def test_a_killed_worker_does_not_change_the_output(scan, clean_output, tmp_path):
    out = tmp_path / "out.laz"
    job = subprocess.Popen(command(scan, out), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    wait_for_tiles(job, out, 2)
    workers = [p for p in psutil.Process(job.pid).children(recursive=True)
               if "spawn_main" in " ".join(p.cmdline()) and "resource_tracker" not in " ".join(p.cmdline())]
    assert len(workers) == 2
    workers[0].kill()
    _, stderr = job.communicate(timeout=300)
    assert job.returncode == 0, stderr
    np.testing.assert_array_equal(laspy.read(out).points.array, clean_output)


def test_a_sigkilled_run_resumes_from_its_finished_tiles(scan, clean_output, tmp_path):
    out = tmp_path / "out.laz"
    job = subprocess.Popen(command(scan, out), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                           start_new_session=True)
    wait_for_tiles(job, out, 3)
    os.killpg(job.pid, signal.SIGKILL)
    job.wait()
    assert not out.exists()  # nothing under the final name
    done = finished_tiles(out)
    rerun = subprocess.run(command(scan, out), capture_output=True, text=True)
    assert rerun.returncode == 0, rerun.stderr
    assert done >= 3 and f"{done} finished earlier" in rerun.stdout
    np.testing.assert_array_equal(laspy.read(out).points.array, clean_output)
    assert not list(tmp_path.glob(".out.laz.*"))  # the work folder and any temporaries are gone


def test_a_work_folder_left_damaged_is_made_again_where_damaged(tmp_path, street_scan, monkeypatch):
    """Files renamed into the work folder before the disk held them can be short after a crash or reboot: a
    truncated tile result, an empty survey, a stored piece cut short, the store's layout file gone. Each rerun
    failed alike (a traceback, or 'Aborted!'); it now makes those parts again and writes the same output."""
    import pipeline
    from pipeline.engine.workdir import WorkDir

    settings = dict(ratio=0.1, method="learned", tile_size=8.0, workers=1)
    clean = tmp_path / "clean.laz"
    pipeline.run(street_scan, clean, **settings)
    out = tmp_path / "out.laz"
    with monkeypatch.context() as kept:  # the finished run's folder stays, as a crash before its removal leaves it
        kept.setattr(WorkDir, "remove", lambda self: None)
        pipeline.run(street_scan, out, **settings)
    [work] = tmp_path.glob(".out.laz.work-*")
    out.unlink()
    tile = sorted(work.glob("tile-*.npz"))[-1]
    tile.write_bytes(tile.read_bytes()[:100])
    (sorted(work.glob("survey-*.npz"))[0]).write_bytes(b"")
    rows = work / "tiles" / "p0.rows"
    rows.write_bytes(rows.read_bytes()[:1000])
    with pytest.warns(pipeline.PipelineNote, match=r"unreadable file\(s\) of an earlier attempt made again") as said:
        pipeline.run(street_scan, out, **settings)
    assert "piece-0.npz" in str(said[0].message) and tile.name in str(said[0].message)
    assert np.array_equal(laspy.read(out).points.array, laspy.read(clean).points.array)
    with monkeypatch.context() as kept:  # now with the store's layout file gone
        kept.setattr(WorkDir, "remove", lambda self: None)
        pipeline.run(street_scan, tmp_path / "again.laz", **settings)
    [again] = tmp_path.glob(".again.laz.work-*")
    (again / "tiles" / "store.json").unlink()
    (tmp_path / "again.laz").unlink()
    with pytest.warns(pipeline.PipelineNote, match="piece-0.npz"):
        pipeline.run(street_scan, tmp_path / "again.laz", **settings)
    assert np.array_equal(laspy.read(tmp_path / "again.laz").points.array, laspy.read(clean).points.array)


def test_work_folders_no_run_can_resume_go_once_the_output_is_written(tmp_path, street_scan, monkeypatch):
    """A changed command starts afresh, and the earlier command's folder (the scan's size, uncompressed) stayed for
    ever; once the output is written, such folders for it go, but not one a run still holds."""
    import fcntl

    import pipeline
    from pipeline.engine.workdir import LOCK, WorkDir

    out = tmp_path / "out.laz"
    for ratio in (0.3, 0.2):  # two earlier commands, each stopped before its folder was removed
        with monkeypatch.context() as kept:
            kept.setattr(WorkDir, "remove", lambda self: None)
            kept.setattr(WorkDir, "remove_others", lambda self, output: [])
            pipeline.run(street_scan, out, ratio=ratio, method="random", workers=1, overwrite=True)
    earlier = sorted(tmp_path.glob(".out.laz.work-*"))
    assert len(earlier) == 2
    with open(earlier[0] / LOCK, "a") as held:  # a run working in the first one
        fcntl.flock(held, fcntl.LOCK_EX)
        with pytest.warns(pipeline.PipelineNote, match="removed 1 work folder"):
            pipeline.run(street_scan, out, ratio=0.1, method="random", workers=1, overwrite=True)
    assert sorted(tmp_path.glob(".out.laz.work-*")) == [earlier[0]]


def test_a_shared_scratch_keeps_the_folders_of_other_outputs_of_one_name(tmp_path, street_scan):
    """Two outputs of one file name in other folders share a --scratch: writing one leaves the other's work."""
    import pipeline

    scratch, first, second = tmp_path / "scratch", tmp_path / "a" / "out.laz", tmp_path / "b" / "out.laz"
    for folder in (scratch, first.parent, second.parent):
        folder.mkdir()
    other = scratch / ".out.laz.work-0123456789abcdef"  # the first output's, from a killed run
    other.mkdir()
    (other / "manifest.json").write_text(json.dumps({"output": str(first)}))
    pipeline.run(street_scan, second, ratio=0.1, method="random", workers=1, scratch=scratch)
    assert other.is_dir()


def test_a_resume_needs_only_the_scratch_space_its_work_folder_does_not_hold_yet(tmp_path, street_scan, monkeypatch):
    """A run stopped by a full scratch disk kept its work; once room was made, the re-run was refused, as its
    space check counted the whole need again, where what the folder held would have let it finish. Compared here:
    the space a resumed run asks the disk for, against a fresh run's."""
    import pipeline
    from pipeline.engine import preflight
    from pipeline.engine.workdir import WorkDir

    settings = dict(ratio=0.1, method="learned", workers=1)
    with monkeypatch.context() as kept:  # an attempt that stopped once its work was done
        kept.setattr(WorkDir, "remove", lambda self: None)
        pipeline.run(street_scan, tmp_path / "out.laz", **settings)
    (tmp_path / "out.laz").unlink()
    [work] = tmp_path.glob(".out.laz.work-*")
    held = sum(path.stat().st_size for path in work.rglob("*") if path.is_file())
    needs = []
    monkeypatch.setattr(preflight, "check_room", lambda folder, need, what, advice: needs.append(need))
    pipeline.run(street_scan, tmp_path / "out.laz", **settings)  # resumed: its need less what it holds
    pipeline.run(street_scan, tmp_path / "fresh.laz", **settings)  # afresh: the whole need
    assert needs[1] - needs[0] == pytest.approx(held, rel=1e-9)
