"""Mesh mode: `pipeline run MESH --mesh` keeps round(ratio * V) vertices and re-triangulates them."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh
from click.testing import CliRunner

from model.meshes import load_mesh
from model.rules import kept_count
from pipeline.apps.cli import cli as pipeline_cli
from pipeline.apps.mesh_mode import _open3d, read_mesh
from pipeline.errors import PipelineError
from tests.test_cli import assert_one_line_error, cli


@pytest.fixture(scope="module")
def sphere_off(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A unit icosphere of 642 vertices as an OFF file."""
    path = tmp_path_factory.mktemp("mesh") / "sphere.off"
    trimesh.creation.icosphere(subdivisions=3).export(path)
    return path


@pytest.mark.parametrize("method", ["learned", "paper", "fps"])
def test_mesh_mode_writes_every_kept_vertex_and_triangles(tmp_path, sphere_off, method):
    out = tmp_path / f"{method}.ply"
    result = CliRunner().invoke(pipeline_cli, ["run", str(sphere_off), "--ratio", "0.1", "--mesh", "-m", method,
                                               "-o", str(out)])
    assert result.exit_code == 0, result.output
    mesh = trimesh.load(out, process=False)
    # every kept vertex is written, even one ball pivoting left without a triangle
    assert len(mesh.vertices) == kept_count(0.1, 642) == 64
    assert len(mesh.faces) > 0 and mesh.faces.max() < len(mesh.vertices)
    assert np.abs(np.linalg.norm(mesh.vertices, axis=1) - 1).max() < 0.1  # refinement nudges, stays on the sphere
    assert "64 of 642 vertices" in result.output
    assert not list(tmp_path.glob(".*tmp*"))  # the temporary name was renamed away


@pytest.mark.parametrize("shape, triangulated", [("flat", True), ("one point", False)])
def test_a_flat_or_collapsed_mesh_is_simplified_not_a_qhull_traceback(tmp_path, shape, triangulated):
    """A flat patch (terrain, a facade, a CAD face) is triangulated: Qhull cannot orient its normals over a
    3-D Delaunay of coplanar points, so they are turned to one side of the plane; vertices all at one place
    give the kept vertices and no triangle. Both were a Qhull traceback."""
    grid = np.stack(np.meshgrid(np.arange(30.0), np.arange(30.0)), axis=-1).reshape(-1, 2)
    vertices = np.column_stack([grid, np.zeros(len(grid))]) if shape == "flat" else np.ones((900, 3))
    faces = np.array([[0, 1, 30], [1, 31, 30]])  # a mesh needs faces; ball pivoting makes its own
    source, out = tmp_path / "patch.off", tmp_path / "out.ply"
    trimesh.Trimesh(vertices, faces, process=False).export(source)
    result = CliRunner().invoke(pipeline_cli, ["run", str(source), "-r", "0.2", "--mesh", "-m", "fps", "-o", str(out)])
    assert result.exit_code == 0, result.output
    mesh = trimesh.load(out, process=False)  # a PointCloud where no face was written
    faces = len(getattr(mesh, "faces", ()))
    assert len(mesh.vertices) == 180 and (faces > 180 if triangulated else faces == 0)


def test_fps_mesh_vertices_are_source_vertices(tmp_path, sphere_off):
    out = tmp_path / "fps.obj"
    assert CliRunner().invoke(pipeline_cli, ["run", str(sphere_off), "-r", "0.2", "--mesh", "-m", "fps",
                                             "-o", str(out)]).exit_code == 0
    kept = load_mesh(out).vertices
    source = {tuple(v) for v in np.round(trimesh.load(sphere_off, process=False).vertices, 6)}
    assert len(kept) == 128 and all(tuple(v) in source for v in np.round(kept, 6))


def test_missing_mesh_is_one_line_and_exit_2(tmp_path):
    out = tmp_path / "out.ply"
    assert_one_line_error(cli("run", str(tmp_path / "nope.off"), "--ratio", "0.1", "--mesh", "-o", str(out)),
                          "nope.off", "no such mesh file")
    assert not out.exists()


def test_point_cloud_without_faces_is_refused(tmp_path):
    cloud = tmp_path / "cloud.ply"
    trimesh.PointCloud(np.random.default_rng(0).normal(size=(100, 3))).export(cloud)
    assert_one_line_error(cli("run", str(cloud), "--ratio", "0.1", "--mesh", "-o", str(tmp_path / "o.ply")),
                          "no triangles")


def test_unreadable_mesh_and_bad_output_are_one_line_errors(tmp_path, sphere_off):
    broken = tmp_path / "broken.off"
    broken.write_text("OFF\n3 1 0\n0 0 0\n")
    with pytest.raises(PipelineError, match="not a readable mesh"):
        read_mesh(broken)
    result = CliRunner().invoke(pipeline_cli, ["run", str(sphere_off), "-r", "0.1", "--mesh",
                                               "-o", str(tmp_path / "o.las")])
    assert result.exit_code == 2 and "unsupported output type (use .ply, .obj, .off)" in result.output
    existing = tmp_path / "kept.ply"
    existing.write_text("mine")
    result = CliRunner().invoke(pipeline_cli, ["run", str(sphere_off), "-r", "0.1", "--mesh", "-o", str(existing)])
    assert result.exit_code == 2 and "already exists" in result.output and existing.read_text() == "mine"


def test_obj_with_per_corner_normals_keeps_shared_vertices(tmp_path):
    obj = tmp_path / "quad.obj"
    obj.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvn 0 0 1\nvn 0 0 -1\nf 1//1 2//1 3//1\nf 1//2 3//2 4//2\n")
    vertices, faces = read_mesh(obj)
    assert len(vertices) == 4 and faces.tolist() == [[0, 1, 2], [0, 2, 3]]


def test_missing_open3d_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "open3d", None)  # makes `import open3d` raise ImportError
    with pytest.raises(PipelineError, match=r"pip install 'lidar-simplify\[mesh\]'"):
        _open3d()


def test_options_mesh_mode_does_not_use_are_refused(tmp_path, sphere_off):
    """--tile-size, --keep-class and the like were taken and silently ignored: one line instead."""
    for flag, value in (("--tile-size", "5"), ("--keep-class", "2"), ("--workers", "1")):
        result = cli("run", str(sphere_off), "-r", "0.2", "--mesh", "-o", str(tmp_path / "out.ply"), flag, value)
        assert_one_line_error(result, f"{flag} does not apply")
    assert not (tmp_path / "out.ply").exists()
