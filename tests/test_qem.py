"""Mesh baselines of the paper's tables: QEM decimation to an exact vertex count, and the uniform vertex subset."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from model.baselines import uniform_vertices
from model.meshes import mesh_graph
from model.qem import qem_vertices
from model.rules import kept_count


@pytest.mark.parametrize("ratio", [0.5, 0.2, 0.1, 0.05, 0.01])
def test_qem_hits_the_vertex_count_and_stays_on_the_sphere(ratio):
    sphere = trimesh.creation.icosphere(subdivisions=4)  # 2,562 vertices on the unit sphere
    kept = qem_vertices(sphere.vertices, sphere.faces, ratio)
    assert kept.shape == (kept_count(ratio, len(sphere.vertices)), 3)
    # collapsed vertices sit at quadric-optimal points near the sphere (chords sag inside it)
    assert np.abs(np.linalg.norm(kept, axis=1) - 1).max() < 0.1


def test_qem_on_an_open_surface_with_sharp_edges():
    box = trimesh.creation.box(extents=(2, 2, 2)).subdivide().subdivide().subdivide()
    kept = qem_vertices(box.vertices, box.faces, 0.1)
    assert len(kept) == kept_count(0.1, len(box.vertices))
    np.testing.assert_allclose(np.abs(kept).max(axis=1), 1, atol=1e-6)  # every vertex stays on a face of the cube


def test_qem_ignores_vertices_off_the_surface():
    sphere = trimesh.creation.icosphere(subdivisions=3)
    stray = np.vstack([sphere.vertices, [[5.0, 5.0, 5.0]]])
    kept = qem_vertices(stray, sphere.faces, 0.2)
    assert len(kept) == kept_count(0.2, len(stray))
    assert np.linalg.norm(kept, axis=1).max() < 1.1  # the stray vertex (at 8.7) is gone


def test_uniform_vertices_exact_seeded_and_real():
    vertices = np.random.default_rng(0).normal(size=(1_001, 3))
    first = uniform_vertices(vertices, 0.1, seed=3)
    assert first.shape == (100, 3)
    np.testing.assert_array_equal(first, uniform_vertices(vertices, 0.1, seed=3))
    assert not np.array_equal(first, uniform_vertices(vertices, 0.1, seed=4))
    rows = {tuple(v) for v in vertices}
    assert all(tuple(v) in rows for v in first) and len({tuple(v) for v in first}) == 100


def test_mesh_graph_rows_hold_the_one_ring_first():
    sphere = trimesh.creation.icosphere(subdivisions=3)
    graph = mesh_graph(np.asarray(sphere.vertices), np.asarray(sphere.faces), 16)
    assert graph.shape == (len(sphere.vertices), 16)
    np.testing.assert_array_equal(graph[:, 0], np.arange(len(graph)))
    for vertex, ring in enumerate(sphere.vertex_neighbors):
        assert len(set(graph[vertex])) == 16
        assert set(graph[vertex, 1 : 1 + len(ring)]) == set(ring)


def test_mesh_graph_fills_short_rows_by_distance():
    triangle = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 0], [6, 5, 0]])
    graph = mesh_graph(triangle, np.array([[0, 1, 2]]), 4)
    np.testing.assert_array_equal(graph[0], [0, 1, 2, 3])  # its ring, then the nearest other vertex
    np.testing.assert_array_equal(graph[4], [4, 3, 1, 2])  # off the mesh: its nearest vertices
