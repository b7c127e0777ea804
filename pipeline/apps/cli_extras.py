"""The commands beside the main job: `pipeline demo` (simulate a street scan and simplify it) and the two
training commands (`train`: the paper's network; `train-detail`: the default method's predictor)."""
from __future__ import annotations

import sys
from pathlib import Path

import click

from pipeline.config import build_config
from pipeline.errors import Interrupted, PipelineError, raise_if_stopped, signal_exit_code
from pipeline.progress import Progress

MIN_POINTS = 16  # vertices drawn per mesh per step: the network's 16-neighbour graph needs as many
MAX_THREADS = 256  # torch threads: more only contend for the cores (100000 ran out of memory)


@click.command("demo")
@click.option("--out-dir", type=click.Path(path_type=Path), default=Path("demo"), show_default=True,
              help="Folder for the demo scan and its simplification.")
@click.option("--points", type=int, default=1_500_000, show_default=True, help="Size of the simulated scan.")
@click.option("--ratio", type=float, default=0.1, show_default=True, help="Fraction of points to keep.")
@click.option("--workers", "-w", type=int, default=None, help="Dask worker processes. [default: 2]")
@click.option("--platform", type=click.Choice(["mobile", "airborne"]), default="mobile", show_default=True,
              help="Scan the street from a car (mobile) or from an aircraft 80 m above it (airborne).")
def demo_command(out_dir: Path, points: int, ratio: float, workers: int | None, platform: str) -> None:
    """Simulate a street scan and simplify it: the built-in end-to-end example."""
    from pipeline.engine.runner import run_scan
    from pipeline.simulate import write_street_scan

    if points < 1:
        raise PipelineError(f"--points must be 1 or more, got {points}")
    settings = build_config("toronto3d" if platform == "mobile" else "airborne", ratio=ratio, workers=workers)
    out_dir.mkdir(parents=True, exist_ok=True)
    stem = "demo_street" if platform == "mobile" else "demo_airborne"
    scan = out_dir / f"{stem}.laz"
    if demo_points(scan) != points:  # none yet, or one of another --points: simulated (again)
        click.echo(f"simulating {points:,} points of {platform} street scan -> {scan}")
        write_street_scan(scan, n_points=points, seed=0, platform=platform)
    report = run_scan([scan], out_dir / f"{stem}.simplified.laz", settings, overwrite=True,
                      progress=Progress.for_terminal())
    click.echo(f"{report.output}: {report.output_points:,} of {report.input_points:,} points "
               f"({report.tiles} tiles, {report.seconds:.1f} s)")


def demo_points(scan: Path) -> int | None:
    """The points of an earlier demo's scan, as its header says; None if there is none (or it is unreadable)."""
    import laspy

    try:
        with laspy.open(scan) as reader:
            return int(reader.header.point_count)
    except (OSError, laspy.LaspyException):
        return None


@click.command("train")
@click.option("--data", type=click.Path(path_type=Path, file_okay=False), required=True,
              help="Folder of TOSCA-style meshes (.off, .off.gz, .obj, .ply); split 80/20 by pose within class.")
@click.option("--out", type=click.Path(path_type=Path), default=Path("tosca.pt"), show_default=True,
              help="Where to save the weights (.pt), with the split and the losses.")
@click.option("--epochs", type=click.IntRange(min=1), default=150, show_default=True,
              help="Passes over the training meshes.")
@click.option("--points", type=click.IntRange(min=MIN_POINTS), default=2048, show_default=True,
              help="Vertices drawn per mesh per step.")
@click.option("--curvature-weight", type=click.FloatRange(min=0), default=0.1, show_default=True,
              help="lambda of the CE term.")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True)
@click.option("--threads", type=click.IntRange(min=1, max=MAX_THREADS), default=1, show_default=True,
              help="torch threads.")
@click.option("--overwrite", is_flag=True, help="Replace an existing --out.")
def train_command(data: Path, out: Path, epochs: int, points: int, curvature_weight: float, seed: int,
                  threads: int, overwrite: bool) -> None:
    """Train the paper's network (`--method paper`) on meshes; CPU, about 20 s an epoch at defaults."""
    check_training(data, [out], overwrite)
    import torch

    from model.learning.training import CHECKPOINT_EVERY, TrainSettings, train

    raise_if_stopped()  # a Ctrl-C while the imports above ran: trimesh swallows it, and training went on
    torch.set_num_threads(threads)
    before = out.stat().st_mtime_ns if out.exists() else None
    try:
        record = train(data, out, TrainSettings(epochs=epochs, points=points, curvature_weight=curvature_weight,
                                                seed=seed), show_progress=sys.stderr.isatty(),
                       log=lambda line: None if sys.stderr.isatty() else click.echo(line, err=True))
    except KeyboardInterrupt as exc:  # a checkpoint saved before the stop is a whole, part-trained file: say so
        if out.exists() and out.stat().st_mtime_ns != before:
            raise Interrupted(f"interrupted; {out} holds the last checkpoint (saved every {CHECKPOINT_EVERY} "
                              "epochs: its record's history says how many ran)", signal_exit_code(exc)) from None
        raise
    last = record.history[-1]
    click.echo(f"{out}: {len(record.train)} training / {len(record.test)} test meshes, {epochs} epochs in "
               f"{record.seconds / 60:.1f} min; final loss {last['loss']:.5f} (CD {last['chamfer']:.5f}, "
               f"CE {last['curvature_error']:.4f})")


@click.command("train-detail")
@click.option("--data", type=click.Path(path_type=Path, file_okay=False), required=True,
              help="Folder of TOSCA-style meshes; the same 80/20 split by pose within class as `train`.")
@click.option("--out", type=click.Path(path_type=Path), default=Path("detail.pt"), show_default=True,
              help="Where to save the weights (.pt, with the split and the test scores; the .npz the default "
                   "method reads goes beside it).")
@click.option("--epochs", type=click.IntRange(min=1), default=12, show_default=True)
@click.option("--views", type=click.IntRange(min=1), default=3, show_default=True,
              help="Scanner views of each training mesh.")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True)
@click.option("--overwrite", is_flag=True, help="Replace an existing --out and its .npz.")
def train_detail_command(data: Path, out: Path, epochs: int, views: int, seed: int, overwrite: bool) -> None:
    """Train the curvature-loss predictor of the default `learned` method (model/detail.py); about 4 min on 2 cores."""
    check_training(data, [out, out.with_suffix(".npz")], overwrite)
    from model.learning.detail_training import DetailSettings, train_detail

    raise_if_stopped()  # a Ctrl-C while the imports above ran: trimesh swallows it, and training went on
    record = train_detail(data, out, DetailSettings(epochs=epochs, views_per_mesh=views, seed=seed),
                          log=lambda line: click.echo(line, err=True))
    last = record["history"][-1]
    click.echo(f"{out}: {len(record['train'])} training / {len(record['test'])} test meshes in "
               f"{record['seconds'] / 60:.1f} min; test correlation {last['test_correlation']:.3f}")


def check_training(data: Path, outputs: list[Path], overwrite: bool) -> None:
    """Before any training: a folder holding meshes (an empty one trained on nothing and wrote its untrained
    weights), and weights files that replace nothing unasked (the defaults were the package's own weights'
    paths, relative to where the command ran: from a checkout, they overwrote the shipped weights)."""
    from model.meshes import MESH_SUFFIXES, list_meshes, mesh_name, stratified_split
    from pipeline.apps.mesh_mode import read_mesh
    from pipeline.io.output_guard import check_output

    if not data.is_dir():
        raise PipelineError(f"{data}: no such folder of meshes")
    meshes = list_meshes(data)
    if not meshes:
        raise PipelineError(f"{data}: no mesh files ({', '.join(MESH_SUFFIXES)}) to train on")
    if not all(stratified_split([mesh_name(path) for path in meshes])):
        raise PipelineError(f"{data}: the split by pose within class left no training or no test mesh: give a "
                            "class (a name before its pose number, as cat0, cat1) two poses or more")
    for path in meshes:  # a bad file in one line naming it, before any training (a traceback or 'Aborted!')
        read_mesh(path)
    if outputs[0].suffix.lower() != ".pt":  # train-detail's .npz would have been written over its own record
        raise PipelineError(f"{outputs[0]}: --out names the .pt file the weights and their record go to")
    for path in outputs:
        path.parent.mkdir(parents=True, exist_ok=True)
        check_output(path, [], overwrite, (path.suffix.lower(),))
