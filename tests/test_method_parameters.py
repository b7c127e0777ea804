"""A method's parameters: given by a config file's [method.<name>] table, the API's `method_parameters` or a
simplifier object; checked in one line; carried to the workers; part of the work folder's key without
being listed anywhere; recorded in an output's provenance where they differ from the defaults."""
from __future__ import annotations

import pickle
import subprocess
import sys
from pathlib import Path

import laspy
import numpy as np
import pytest

import pipeline
from model.learning import DETAIL_WEIGHTS, PAPER_WEIGHTS
from model.methods import Paper, Voxel
from model.registry import REGISTERED, get_simplifier, method_name
from pipeline.config import build_config
from pipeline.engine.workdir import output_settings, run_key
from pipeline.errors import PipelineError
from pipeline.io.provenance import read_provenance
from tests.test_units import write_patch


def test_registered_methods_are_picklable_values():
    for method in REGISTERED.values():
        assert pickle.loads(pickle.dumps(method)) == method and hash(method) == hash(pickle.loads(pickle.dumps(method)))
    assert get_simplifier("paper", refine=True) == REGISTERED["paper-refined"]
    assert method_name(Paper(refine=True)) == "paper" and method_name(Voxel(slack=0.1)) == "voxel"


def test_parameters_from_a_config_table_the_api_and_an_object(tmp_path):
    path = tmp_path / "run.toml"
    path.write_text('[run]\nmethod = "voxel"\n[method.voxel]\nslack = 0.1\n[method.learned]\ncover_spacings = 3\n')
    assert build_config(str(path)).simplifier == Voxel(slack=0.1)
    assert build_config(str(path), method="learned").simplifier.cover_spacings == 3.0  # an int where a float goes
    assert build_config(str(path), method_parameters={"slack": 0.2}).simplifier == Voxel(slack=0.2)  # API wins
    assert build_config(method=Voxel(slack=0.3)).simplifier == Voxel(slack=0.3)
    assert build_config(method="fps").method_parameters == ()


@pytest.mark.parametrize("text, message", [
    ('[run]\nmethod = "voxel"\n[method.voxel]\nslak = 0.1\n', "method 'voxel' has no parameter 'slak' (it takes: slack)"),
    ('[run]\nmethod = "voxel"\n[method.voxel]\nslack = "much"\n', "parameter 'slack' must be a number, got 'much'"),
    ('[run]\nmethod = "fps"\n[method.fps]\nslack = 0.1\n', "method 'fps' has no parameter 'slack' (it takes: no parameters)"),
    ('[run]\nmethod = "learned"\n[method.learned]\ndetail = -1\n', "parameter 'detail' must be a number >= 0, got -1"),
    ('[run]\nmethod = "learned"\n[method.learned]\nchamfer_bound = 0\n',
     "parameter 'chamfer_bound' must be a positive number, got 0.0"),
    ('[method.voxl]\nslack = 0.1\n', "[method.voxl]: unknown method"),
    ('[method]\nslack = 0.1\n', "[method] must hold one table per method"),
    (f'[run]\nmethod = "learned"\n[method.learned]\nweights = "{PAPER_WEIGHTS}"\n',
     f"{PAPER_WEIGHTS} is not the detail predictor's weights"),  # not in the first tile, after the work began
    (f'[run]\nmethod = "paper"\n[method.paper]\nweights = "{DETAIL_WEIGHTS}"\n',
     f"{DETAIL_WEIGHTS} is not a torch checkpoint of the paper's network"),
    ('[run]\nseed = -1\n', "--seed must be a whole number, 0 or more, got -1"),
    ('[run]\nmethod = "fps"\n[method.voxel]\nslak = 0.1\n',  # a table the run does not use is checked too
     "[method.voxel]: method 'voxel' has no parameter 'slak'"),
    ('[method.voxel]\nslack = "x"\n', "run.toml: [method.voxel]: parameter 'slack' must be a number"),
])
def test_a_bad_parameter_is_one_line(tmp_path, text, message):
    path = tmp_path / "run.toml"
    path.write_text(text)
    with pytest.raises(PipelineError) as caught:
        build_config(str(path))
    assert message in str(caught.value) and "\n" not in str(caught.value)


def test_the_work_folder_key_follows_every_parameter_and_provenance_the_changed_ones(tmp_path):
    scan = tmp_path / "scan.las"
    write_patch(scan, 26917, 1.0, n=4_000)
    default, same, changed = (build_config(method="voxel"), build_config(method=Voxel()),
                              build_config(method="voxel", method_parameters={"slack": 0.1}))
    assert run_key([scan], default) == run_key([scan], same) != run_key([scan], changed)
    assert "method_parameters" not in output_settings(default)  # outputs of default runs stay as they were
    assert output_settings(changed)["method_parameters"] == {"slack": 0.1}


def test_the_work_folder_key_follows_the_weights_contents_not_their_place(tmp_path):
    """Weights changed in place resumed a killed run (and skipped a batch job) with the old ones; the same weights
    elsewhere (an install moved) resumed nothing: the key reads their digest, not their path."""
    import numpy as np

    scan = tmp_path / "scan.las"
    write_patch(scan, 26917, 1.0, n=2_000)
    here, there = tmp_path / "a" / "detail.npz", tmp_path / "b" / "detail.npz"
    for copy in (here, there):
        copy.parent.mkdir()
        copy.write_bytes(DETAIL_WEIGHTS.read_bytes())

    def key(weights: Path) -> str:
        return run_key([scan], build_config(method="learned", method_parameters={"weights": str(weights)}))

    assert key(here) == key(there)
    with np.load(here) as saved:
        arrays = {name: saved[name] for name in saved.files}
    np.savez(here, **{**arrays, "shift": arrays["shift"] + 1})
    assert key(here) != key(there)


def test_a_parameter_reaches_the_workers(tmp_path):
    """A cluster run (pickled jobs) with a looser voxel slack keeps other points than the default, and the
    output records the parameter."""
    scan = tmp_path / "scan.las"
    write_patch(scan, 26917, 1.0, n=30_000)
    # unmerged 20 m tiles: several tasks, on which the two slacks settle on different cells (merged into one
    # tile, both searches happened to stop at the same cell)
    settings = dict(ratio=0.1, tile_size=20.0, merge_tile_points=0, workers=1, in_process_points=0)
    pipeline.run(scan, tmp_path / "default.las", method="voxel", **settings)
    pipeline.run(scan, tmp_path / "loose.las", method=Voxel(slack=0.5), **settings)
    default, loose = laspy.read(tmp_path / "default.las"), laspy.read(tmp_path / "loose.las")
    assert len(default.points) == len(loose.points) == 3_000
    assert not np.array_equal(np.sort(default.X), np.sort(loose.X))
    assert read_provenance(loose.header)["settings"]["method_parameters"] == {"slack": 0.5}
    assert "method_parameters" not in read_provenance(default.header)["settings"]


def test_a_tiles_survey_reaches_its_simplify_step(tmp_path, monkeypatch):
    """The voxel counts a run's survey measured reach each tile's method (its voxel search starts there),
    with the survey's doubling edges, and they are the tile's own (tiles differ)."""
    import model.methods

    seen = []
    voxel_simplify = model.methods.voxel_simplify
    monkeypatch.setattr(model.methods, "voxel_simplify",
                        lambda tile, budget, slack: seen.append(tile.voxels) or voxel_simplify(tile, budget, slack))
    scan = tmp_path / "scan.las"
    write_patch(scan, 26917, 1.0, n=30_000)
    pipeline.run(scan, tmp_path / "out.las", method="voxel", ratio=0.1, tile_size=20.0, merge_tile_points=0)
    assert len(seen) > 1 and all(survey is not None for survey in seen)
    assert all(np.allclose(survey.sizes[1:], 2 * survey.sizes[:-1]) and survey.counts[0] > 0 for survey in seen)
    assert len({tuple(survey.counts) for survey in seen}) > 1


def test_cli_param_flags_reach_the_output(tmp_path):
    scan, out = tmp_path / "scan.las", tmp_path / "out.las"
    write_patch(scan, 26917, 1.0, n=4_000)
    subprocess.run([sys.executable, "-m", "pipeline.apps.cli", "run", str(scan), "-r", "0.1", "-m", "voxel", "-p",
                    "slack=0.25", "-o", str(out), "-q"], check=True)
    assert read_provenance(laspy.open(out).header)["settings"]["method_parameters"] == {"slack": 0.25}
    for bad, said in (("slack", "--param takes NAME=VALUE, got 'slack'"), ("slack=true", "must be a number")):
        result = subprocess.run([sys.executable, "-m", "pipeline.apps.cli", "run", str(scan), "-r", "0.1", "-m",
                                 "voxel", "-p", bad, "-o", str(tmp_path / "bad.las")], capture_output=True, text=True)
        assert result.returncode == 2 and said in result.stderr and result.stderr.count("\n") == 1


def test_the_cli_names_a_bad_parameter_in_one_line(tmp_path):
    scan, config = tmp_path / "scan.las", tmp_path / "run.toml"
    write_patch(scan, 26917, 1.0, n=2_000)
    config.write_text('[method.voxel]\nslack = -1\n')
    result = subprocess.run([sys.executable, "-m", "pipeline.apps.cli", "run", str(scan), "-r", "0.1", "-m", "voxel",
                             "-c", str(config), "-o", str(tmp_path / "out.las")], capture_output=True, text=True)
    assert result.returncode == 2 and result.stderr.count("\n") == 1
    assert "slack" in result.stderr and not (tmp_path / "out.las").exists()


def test_batch_param_flags_reach_every_job_and_a_changed_one_reruns(tmp_path):
    scans, out = tmp_path / "scans", tmp_path / "out"
    scans.mkdir()
    write_patch(scans / "a.las", 26917, 1.0, n=3_000)
    command = [sys.executable, "-m", "pipeline.apps.cli", "batch", str(scans), "--out-dir", str(out), "-r", "0.1",
               "-m", "voxel"]
    said = [subprocess.run(command + ["-p", f"slack={slack}"], capture_output=True, text=True, check=True).stdout
            for slack in (0.3, 0.3, 0.1)]
    assert "1 done, 0 already done" in said[0] and "0 done, 1 already done" in said[1]
    assert "1 done, 0 already done" in said[2]  # the work folder's and manifest's key read the parameters
    assert read_provenance(laspy.open(out / "a.simplified.las").header)["settings"]["method_parameters"] == {
        "slack": 0.1}


def test_detail_reaches_the_budgets_and_the_tiles(tmp_path):
    """`detail` reaches every tile of a run and its budgets: 0 and 2 each keep other points than the default
    (several tiles, so the budgets matter), and the output records the parameter."""
    scan = tmp_path / "scan.las"
    write_patch(scan, 26917, 1.0, n=30_000)
    settings = dict(ratio=0.1, tile_size=20.0, merge_tile_points=0, workers=1)
    for name, parameters in (("default", {}), ("none", {"detail": 0.0}), ("strong", {"detail": 2.0})):
        pipeline.run(scan, tmp_path / f"{name}.las", method="learned", method_parameters=parameters, **settings)
    default, none, strong = (laspy.read(tmp_path / f"{name}.las") for name in ("default", "none", "strong"))
    assert len(default.points) == len(none.points) == len(strong.points) == 3_000
    for other in (none, strong):
        assert not np.array_equal(np.sort(other.X), np.sort(default.X))
    assert read_provenance(strong.header)["settings"]["method_parameters"] == {"detail": 2.0}
    assert "method_parameters" not in read_provenance(default.header)["settings"]
