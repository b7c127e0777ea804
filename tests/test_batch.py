"""`pipeline batch` (a folder or a TOML job list, one manifest, reruns skip finished work) and --log-json."""
from __future__ import annotations

import json
import os
from pathlib import Path

import laspy
import pytest

from tests.test_cli import assert_one_line_error, cli, small_las


@pytest.fixture()
def scans(tmp_path: Path) -> Path:
    folder = tmp_path / "scans"
    folder.mkdir()
    small_las(folder / "a.las", 3_000)
    small_las(folder / "b.las", 2_000)
    (folder / "broken.laz").write_bytes(b"not a laz file at all")
    return folder


def events(stdout: str) -> list[dict]:
    return [json.loads(line) for line in stdout.splitlines()]


def test_folder_batch_records_each_scan_and_reruns_only_what_failed(scans, tmp_path):
    out = tmp_path / "out"
    first = cli("batch", str(scans), "--out-dir", str(out), "--ratio", "0.1", "--method", "random", "-w", "1",
                "--log-json")
    assert first.returncode == 1  # one scan failed
    log = events(first.stdout)
    assert [e["event"] for e in log if e["event"] in ("done", "failed")] == ["done", "done", "failed"]
    assert all("time" in e for e in log) and log[-1] == {**log[-1], "event": "batch", "done": 2, "failed": 1}
    manifest = json.loads((out / "batch-manifest.json").read_text())
    assert manifest["a.simplified.las"]["status"] == "done"  # by its path from the manifest's folder
    assert manifest["a.simplified.las"]["output_points"] == 300
    assert "broken.laz" in manifest["broken.simplified.laz"]["error"]
    assert len(laspy.read(out / "b.simplified.las").points) == 200
    assert not (out / "broken.simplified.laz").exists()

    (scans / "broken.laz").unlink()
    small_las(scans / "broken.laz", 1_000)  # fixed, as LAS bytes under the same name
    second = cli("batch", str(scans), "--out-dir", str(out), "--ratio", "0.1", "--method", "random", "-w", "1",
                 "--log-json")
    assert second.returncode == 0, second.stderr
    assert [e["event"] for e in events(second.stdout)] == ["skipped", "skipped", "started", "done", "batch"]
    # the same batch from another folder, its out-dir spelled relative: all done (all were 'failed': already exists)
    third = cli("batch", os.path.relpath(scans, tmp_path), "--out-dir", "out", "--ratio", "0.1", "--method", "random",
                "-w", "1", "--log-json", cwd=tmp_path)
    assert third.returncode == 0, third.stderr
    assert [e["event"] for e in events(third.stdout)] == ["skipped", "skipped", "skipped", "batch"]
    assert len(json.loads((out / "batch-manifest.json").read_text())) == 3


def batch_of(tmp_path: Path, defaults: str, jobs: str):
    """`pipeline batch` on a jobs.toml of fps jobs on one worker, writing to small/ unless a job says."""
    path = tmp_path / "jobs.toml"
    path.write_text(f'[defaults]\n{defaults}method = "fps"\nworkers = 1\nout_dir = "small"\n{jobs}')
    result = cli("batch", str(path))
    assert result.returncode == 0, result.stderr
    return result


def test_toml_job_list_with_defaults_and_per_job_settings(scans, tmp_path):
    result = batch_of(tmp_path, "ratio = 0.1\n", f'[[job]]\ninput = "{scans}/a.las"\n[[job]]\ninput = '
                      f'["{scans}/a.las", "{scans}/b.las"]\noutput = "merged.laz"\nratio = 0.5\n')
    assert len(laspy.read(tmp_path / "small" / "a.simplified.las").points) == 300
    assert len(laspy.read(tmp_path / "merged.laz").points) == 2_500
    assert json.loads((tmp_path / "jobs.manifest.json").read_text())["merged.laz"]["status"] == "done"
    assert "batch: 2 done, 0 already done, 0 failed" in result.stdout


def test_a_job_s_own_levels_replace_the_defaults_ratio(scans, tmp_path):
    """[defaults] ratio = 0.1 and one job's levels = [0.2, 0.1] failed the whole batch ('--ratio 0.1 disagrees
    with --levels'): a job's own ratio or levels replace the defaults' output size."""
    batch_of(tmp_path, "ratio = 0.05\n",
             f'[[job]]\ninput = "{scans}/a.las"\nlevels = [0.2, 0.1]\n[[job]]\ninput = "{scans}/b.las"\n')
    counts = {p.name: len(laspy.read(p).points) for p in (tmp_path / "small").glob("*.las")}
    assert counts == {"a.simplified.r0.2.las": 600, "a.simplified.r0.1.las": 300, "b.simplified.las": 100}


@pytest.mark.parametrize("content, words", [
    ("[defaults]\nratio = 0.1\n", ("no [[job]] entries",)),
    ('[[job]]\noutput = "x.laz"\n', ("job 1 has no input",)),
    ("[[job]\n", ("not a readable TOML job list",)),
    ('[[job]]\ninput = "a.las"\noutput = "x.laz"\nratio = 2\n', ("job 1: --ratio must be in (0, 1]",)),
])
def test_bad_job_lists_are_one_line(tmp_path, content, words):
    jobs = tmp_path / "jobs.toml"
    jobs.write_text(content)
    assert_one_line_error(cli("batch", str(jobs)), str(jobs), *words)


def test_a_folder_needs_an_output_folder(scans):
    assert_one_line_error(cli("batch", str(scans), "--ratio", "0.1"), "--out-dir")


def test_run_log_json_reports_success_and_failure(scans, tmp_path):
    ok = cli("run", str(scans / "a.las"), "--ratio", "0.1", "-o", str(tmp_path / "a.laz"), "-m", "random", "-w", "1",
             "--log-json")
    assert ok.returncode == 0, ok.stderr
    (done,) = events(ok.stdout)
    assert done["event"] == "done" and done["output_points"] == 300 and done["input_points"] == 3_000
    assert done["hole_radius_m"] is None and done["floor_tiles"] == 0  # random has no hole cover
    bad = cli("run", str(scans / "a.las"), "--ratio", "2", "-o", str(tmp_path / "b.laz"), "--log-json")
    assert bad.returncode == 2
    (failed,) = events(bad.stdout)
    assert failed["event"] == "failed" and "--ratio" in failed["error"]


def test_a_refused_batch_still_logs_its_outcome_as_json(tmp_path):
    """A batch refused before any job (no such job list, two jobs writing one output) printed its one line on
    stderr only: a log collector reading stdout never saw that the nightly batch did not run."""
    result = cli("batch", str(tmp_path / "missing"), "--out-dir", str(tmp_path / "out"), "--ratio", "0.1", "--log-json")
    assert result.returncode == 2
    [outcome] = events(result.stdout)
    assert outcome["event"] == "failed" and "no such job file or folder" in outcome["error"]


def test_a_bad_flag_value_is_logged_as_json_too(tmp_path):
    """Click refuses `--ratio abc` before the command runs; under --log-json stdout says so in one JSON line."""
    for command in ("run", "batch"):
        result = cli(command, str(tmp_path / "x.laz"), "--ratio", "abc", "--log-json")
        assert result.returncode == 2 and "is not a valid float" in result.stderr
        [outcome] = events(result.stdout)
        assert outcome["event"] == "failed" and "'abc' is not a valid float" in outcome["error"]
