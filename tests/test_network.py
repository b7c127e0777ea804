"""The paper's network and losses: shapes, gradients, known loss values, and that training learns."""
from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from model.learning.losses import adaptive_chamfer, curvature_error, curvature_weights, mean_curvature
from model.learning.network import (LearnedSimplifier, Projector, Refiner, knn_graph, latent_fps, mean_operator,
                                    normalise)
from model.learning.training import TrainSettings, training_step


@pytest.fixture
def cloud() -> tuple[torch.Tensor, torch.Tensor]:
    rng = np.random.default_rng(0)
    xyz, _, _ = normalise(torch.from_numpy(rng.normal(size=(600, 3)).astype(np.float32)))
    return xyz, knn_graph(xyz.numpy())


def test_normalise_fits_the_unit_ball():
    xyz = torch.tensor([[500_000.0, 4e6, 10.0], [500_010.0, 4e6, 10.0], [500_000.0, 4e6 + 4, 13.0]], dtype=torch.float64)
    normalised, centre, scale = normalise(xyz)
    assert torch.allclose(normalised.mean(0), torch.zeros(3, dtype=torch.float64), atol=1e-9)
    assert abs(normalised.norm(dim=1).max().item() - 1) < 1e-9
    assert torch.allclose(normalised * scale + centre, xyz)


def test_projector_shapes_and_gradients(cloud):
    xyz, neighbours = cloud
    projector = Projector()
    features = projector(xyz, mean_operator(neighbours, len(xyz)))
    assert features.shape == (600, 64) and (features >= 0).all()
    features.sum().backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in projector.parameters())


def test_mean_operator_averages_neighbours(cloud):
    xyz, neighbours = cloud
    mean = mean_operator(neighbours, len(xyz))
    expected = xyz[neighbours[:, 1:]].mean(dim=1)
    assert torch.allclose(torch.sparse.mm(mean, xyz), expected, atol=1e-6)


def test_latent_fps_is_exact_fps_and_prefix_stable():
    features = torch.randn(300, 64)
    order = latent_fps(features, 50, start=7)
    assert order[0] == 7 and len(set(order.tolist())) == 50
    chosen, nearest = [7], (features - features[7]).square().sum(1)
    for _ in range(49):  # brute force farthest point sampling
        nxt = int(torch.argmax(nearest))
        chosen.append(nxt)
        nearest = torch.minimum(nearest, (features - features[nxt]).square().sum(1))
    assert order.tolist() == chosen
    assert latent_fps(features, 20, start=7).tolist() == chosen[:20]


def test_refiner_moves_centres_and_passes_gradients(cloud):
    xyz, neighbours = cloud
    features = torch.rand(600, 64, requires_grad=True)
    refiner = Refiner()
    centres = torch.arange(0, 600, 10)
    refined = refiner(xyz, features, centres, neighbours)
    assert refined.shape == (60, 3)
    refined.square().sum().backward()
    assert features.grad.abs().sum() > 0
    assert all(p.grad is not None for p in refiner.parameters())


def test_model_returns_budget_centres(cloud):
    xyz, neighbours = cloud
    centres, refined = LearnedSimplifier()(xyz, neighbours, 123, start=0)
    assert len(set(centres.tolist())) == 123 and refined.shape == (123, 3)


def test_chamfer_known_values():
    a = torch.tensor([[0.0, 0, 0], [1.0, 0, 0]])
    assert adaptive_chamfer(a, a, torch.ones(2)).item() == pytest.approx(0, abs=1e-6)
    b = a + torch.tensor([0.0, 0.1, 0])  # every nearest distance is 0.1
    assert adaptive_chamfer(a, b, torch.ones(2)).item() == pytest.approx(2 * 0.01, rel=1e-5)
    c = torch.tensor([[0.0, 0, 0]])  # a[1] is 1 away from c; c is 0 away from a[0]
    assert adaptive_chamfer(a, c, torch.tensor([1.0, 3.0])).item() == pytest.approx(3 / 4, rel=1e-5)


def test_curvature_error_zero_for_equal_curvature_and_weights_range(cloud):
    xyz, _ = cloud
    k = mean_curvature(xyz)
    assert curvature_error(xyz, k, xyz, k).item() == pytest.approx(0, abs=1e-7)
    assert curvature_error(xyz, k, xyz, k + 0.1).item() == pytest.approx(0.1, rel=1e-4)
    w = curvature_weights(k)
    assert w.min() >= 0.5 and w.max() == pytest.approx(torch.sigmoid(torch.tensor(10.0)).item(), rel=1e-5)


def test_mean_curvature_flat_plane_is_zero_and_edges_high():
    grid = torch.stack(torch.meshgrid(torch.linspace(0, 1, 20), torch.linspace(0, 1, 20), indexing="ij"), -1)
    plane = torch.cat([grid.reshape(-1, 2), torch.zeros(400, 1)], 1)
    assert mean_curvature(plane).abs().max() < 1e-5
    samples, _ = trimesh.sample.sample_surface(trimesh.creation.box(), 3000, seed=1)
    box = torch.from_numpy(samples.astype(np.float32))
    k = mean_curvature(box)
    edge = (box.abs() > 0.45).sum(1) >= 2
    assert k[edge].median() > 3 * k[~edge].median()


def test_a_few_steps_lower_the_loss():
    torch.manual_seed(0)
    mesh = trimesh.creation.icosphere(subdivisions=4)
    vertices = np.asarray(mesh.vertices) * [1.0, 0.6, 0.3]  # an ellipsoid: curvature varies
    settings = TrainSettings(points=800, ratio_min=0.2, ratio_max=0.2)
    model = LearnedSimplifier()
    optimiser = torch.optim.Adam(model.parameters(), lr=1e-3)

    def evaluate() -> float:
        model.eval()
        with torch.no_grad():
            loss = training_step(model, vertices, settings, np.random.default_rng(123))[0].item()
        model.train()
        return loss

    before = evaluate()
    rng = np.random.default_rng(1)
    for _ in range(40):
        loss = training_step(model, vertices, settings, rng)[0]
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    assert evaluate() < 0.8 * before


def test_torch_mean_curvature_matches_geometry_module():
    from model.geometry import point_features

    xyz = np.random.default_rng(2).normal(size=(1500, 3)).astype(np.float32)
    np.testing.assert_allclose(mean_curvature(torch.from_numpy(xyz)).numpy(), point_features(xyz).mean_curvature,
                               atol=1e-5)


def test_folding_batchnorm_keeps_the_projector_outputs(cloud):
    xyz, neighbours = cloud
    projector = Projector()
    projector.train()(xyz, mean_operator(neighbours, len(xyz)))  # move the running statistics off their defaults
    projector.eval()
    with torch.no_grad():
        before = projector(xyz, mean_operator(neighbours, len(xyz)))
        projector.fold_batchnorm()
        after = projector(xyz, mean_operator(neighbours, len(xyz)))
    assert len(projector.pointwise) == 6
    assert torch.allclose(before, after, atol=1e-5)


def test_blockwise_inference_matches_forward(cloud, monkeypatch):
    import model.learning.network as network

    xyz, neighbours = cloud
    projector = Projector()
    projector.train()(xyz, mean_operator(neighbours, len(xyz)))
    projector.eval().fold_batchnorm()
    monkeypatch.setattr(network, "INFERENCE_ROWS", 37)  # several blocks and a short last one
    with torch.no_grad():
        whole = projector(xyz, mean_operator(neighbours, len(xyz)))
    blocks = projector.infer(xyz, neighbours)
    assert len(xyz) % 37 and len(xyz) > 2 * 37
    assert torch.allclose(whole, blocks, atol=1e-5)
