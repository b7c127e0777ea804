"""The default `learned` method: a TOSCA-trained curvature-loss predictor weighting the stratified fill."""
from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree

from model import Tile, get_simplifier
from model.detail import DESCRIBED_PER_PICK, described_tile, descriptors, load_detail_weights, predicted_fill_loss
from model.learning import DETAIL_WEIGHTS, PAPER_WEIGHTS
from model.learning.detail_net import TRAINED, export_weights, load_detail_net


def edge_pole_plane(seed: int = 0) -> tuple[Tile, np.ndarray, np.ndarray]:
    """A floor, a 5 m step up to a roof (a 90-degree edge), and a thin 6 m pole on the floor:
    (tile, points within 0.3 m of the roof edge, pole points)."""
    rng = np.random.default_rng(seed)
    floor = np.column_stack([rng.uniform(0, 10, 20_000), rng.uniform(0, 20, 20_000), np.zeros(20_000)])
    wall = np.column_stack([np.full(10_000, 10.0), rng.uniform(0, 20, 10_000), rng.uniform(0, 5, 10_000)])
    roof = np.column_stack([rng.uniform(10, 20, 10_000), rng.uniform(0, 20, 10_000), np.full(10_000, 5.0)])
    angle = rng.uniform(0, 2 * np.pi, 600)
    pole = np.column_stack([5 + 0.06 * np.cos(angle), 10 + 0.06 * np.sin(angle), rng.uniform(0, 6, 600)])
    xyz = np.concatenate([floor, wall, roof, pole])
    xyz += rng.normal(0, 0.003, xyz.shape)
    near_edge = (np.abs(xyz[:, 0] - 10) < 0.3) & (np.abs(xyz[:, 2] - 5) < 0.3)
    on_pole = np.arange(len(xyz)) >= len(xyz) - len(pole)
    return Tile(xyz - xyz.mean(0), np.ones(len(xyz), dtype=bool), np.zeros(3), seed=3), near_edge, on_pole


def share_kept(kept: np.ndarray, mask: np.ndarray, ratio: float) -> float:
    """Points of the mask kept, over ratio times its points (1 = a uniform thinning's share)."""
    return float(np.isin(np.flatnonzero(mask), kept).sum() / mask.sum() / ratio)


def test_default_keeps_the_edge_and_the_pole_where_uniform_thinning_does_not():
    """Counts near the edge and on the pole, and how close the pole's points stay to a kept point: its 90th
    percentile distance (0.072-0.077 m over seeds 0-3, uniform's 0.118-0.131). Its largest gap, asserted at
    0.7x uniform's until 0.3.11, held for seeds 0 and 2 only (0.68x, 0.54x; 0.84x and 0.71x for 1 and 3), and
    moved to 0.96x at seed 0 when the tile's Chamfer bound narrowed its hole radius (seeds 1-3: 0.53-0.78x): it
    is held below uniform's."""
    tile, near_edge, on_pole = edge_pole_plane()
    ratio = 0.1
    budget = round(ratio * len(tile.xyz))
    learned = get_simplifier("learned")(tile, budget).indices
    uniform = get_simplifier("random")(tile, budget).indices
    assert len(learned) == budget and len(np.unique(learned)) == budget
    assert share_kept(learned, near_edge, ratio) > 1.4 and share_kept(uniform, near_edge, ratio) < 1.25
    assert share_kept(learned, on_pole, ratio) > 2.0 and share_kept(uniform, on_pole, ratio) < 1.5
    pole_gap = {name: cKDTree(tile.xyz[kept]).query(tile.xyz[on_pole])[0]
                for name, kept in (("learned", learned), ("uniform", uniform))}
    assert np.quantile(pole_gap["learned"], 0.9) < 0.7 * np.quantile(pole_gap["uniform"], 0.9)
    assert pole_gap["learned"].max() < pole_gap["uniform"].max()


def test_detail_sets_how_much_the_edge_and_the_pole_keep_and_the_plane_pays_for_it():
    """`detail` scales the loss's share of the keep weights: 0 keeps about a uniform thinning's share on the
    edge and the pole, and each step up to the default keeps more there and less on the floor."""
    from model.methods import Learned

    tile, near_edge, on_pole = edge_pole_plane()
    ratio = 0.1
    budget = round(ratio * len(tile.xyz))
    floor = (np.abs(tile.xyz[:, 2] - tile.xyz[:, 2].min()) < 0.05) & ~on_pole
    shares = {}
    for detail in (0.0, 0.5, 1.0, 4.0):
        kept = Learned(detail=detail)(tile, budget).indices
        assert len(np.unique(kept)) == budget
        shares[detail] = [share_kept(kept, mask, ratio) for mask in (near_edge, on_pole, floor)]
    assert shares[0.0][0] < 1.25 and shares[0.0][1] < 1.5
    for low, high in ((0.0, 0.5), (0.5, 1.0)):
        assert shares[high][0] > shares[low][0] and shares[high][1] > shares[low][1]
        assert shares[high][2] < shares[low][2]
    assert shares[4.0][1] >= shares[1.0][1]  # beyond about 2 the weights follow the loss alone: little changes
    assert Learned() == get_simplifier("learned") and Learned().detail == 1.0


def test_the_loss_is_described_at_the_outputs_scale_and_told_to_the_nearest_points():
    """Below a ratio of 1 / DESCRIBED_PER_PICK a tile is described on an even thinning to that many points
    per pick, core and halo alike; each core point takes the prediction of the nearest described core point
    (a described one its own). At or above it, every point is described."""
    tile, _, _ = edge_pole_plane(4)
    halo = tile.xyz[:, 0] > 8  # a strip of the tile as halo
    tile = Tile(tile.xyz, ~halo, tile.centre, tile.seed)
    budget = tile.core_count // 10
    seen, nearest = described_tile(tile, budget)
    assert seen.core_count == DESCRIBED_PER_PICK * budget
    assert abs((~seen.core).sum() / halo.sum() - DESCRIBED_PER_PICK * budget / tile.core_count) < 1e-3
    described_xyz, core_xyz = seen.xyz[seen.core], tile.xyz[tile.core]
    np.testing.assert_allclose(np.linalg.norm(described_xyz[nearest] - core_xyz, axis=1),
                               cKDTree(described_xyz).query(core_xyz)[0])
    loss = predicted_fill_loss(tile, budget)
    assert (loss.relative[halo] == 0).all() and abs(loss.relative[tile.core].mean() - 1) < 1e-9
    own = load_detail_weights().predict(descriptors(seen, budget))  # the described points keep their own
    at = np.flatnonzero(tile.core)[np.unique(nearest, return_index=True)[1]]
    np.testing.assert_allclose(loss.relative[at] / loss.relative[at].mean(), own / own.mean(), rtol=1e-5)
    whole, everything = described_tile(tile, tile.core_count // DESCRIBED_PER_PICK + 1)
    assert whole is tile and (everything == np.arange(tile.core_count)).all()


def test_descriptors_do_not_depend_on_where_the_tile_is_or_its_unit():
    """Translated and scaled (metres to feet): the same descriptors, the measured-loss column included."""
    tile, _, _ = edge_pole_plane(1)
    moved = Tile(tile.xyz * 3.28084 + [1250.0, -380.5, 42.0], tile.core, tile.centre, tile.seed)
    here, there = descriptors(tile, 2_000), descriptors(moved, 2_000)
    np.testing.assert_allclose(here[:, :11], there[:, :11], atol=2e-4)
    assert np.mean(np.abs(here[:, 11] - there[:, 11]) < 1e-3) > 0.99  # Morton round-off may move a pick


def test_descriptors_of_a_core_do_not_depend_on_the_halo_beyond_its_neighbours():
    """The same core with a 2 m halo and with a 6 m one: the same descriptors and the same prediction
    (its halo serves as neighbours; how wide it is must not change what the core is told)."""
    tile, _, _ = edge_pole_plane(5)
    xy = tile.xyz[:, :2] - tile.xyz[:, :2].min(axis=0)
    core = (xy[:, 0] > 6) & (xy[:, 0] < 14) & (xy[:, 1] > 6) & (xy[:, 1] < 14)
    near = (xy[:, 0] > 4) & (xy[:, 0] < 16) & (xy[:, 1] > 4) & (xy[:, 1] < 16)
    wide = Tile(tile.xyz, core, tile.centre, tile.seed)
    narrow = Tile(tile.xyz[near], core[near], tile.centre, tile.seed)
    np.testing.assert_array_equal(descriptors(wide, 1_000), descriptors(narrow, 1_000))
    assert len(descriptors(wide, 1_000)) == core.sum()


def test_descriptors_and_prediction_do_not_depend_on_the_row_batches(monkeypatch):
    """Descriptors and the prediction are made a batch of rows at a time (memory); rows of 777 instead of
    8,192, and core blocks of 1,000 instead of 32,768, give the same descriptors, and predictions equal
    to float32 round-off (the matrix products' BLAS kernels may sum in another order for another batch
    shape: through three layers that reached 1.2e-6 relative, some ten float32 ulps, in one CI run)."""
    import model.detail
    import model.geometry

    tile, _, _ = edge_pole_plane(2)
    weights = load_detail_weights()
    whole, prediction = descriptors(tile, 4_000), weights.predict(descriptors(tile, 4_000))
    for module in (model.geometry, model.detail):
        monkeypatch.setattr(module, "FRAME_POINTS", 777)
    monkeypatch.setattr(model.detail, "SURVEY_BLOCK", 1_000)  # blocks of core points, each with its own rings
    batched = descriptors(tile, 4_000)
    assert tile.core_count > 5_000
    np.testing.assert_array_equal(batched, whole)
    np.testing.assert_allclose(weights.predict(batched), prediction, rtol=1e-5)


def test_descriptors_of_a_rotated_tile_agree_but_for_the_measured_thinning():
    tile, _, _ = edge_pole_plane(2)
    angle = 0.7
    rotation = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    turned = Tile(tile.xyz @ rotation.T, tile.core, tile.centre, tile.seed)
    np.testing.assert_allclose(descriptors(tile, 2_000)[:, :11], descriptors(turned, 2_000)[:, :11], atol=2e-4)


def test_weights_ship_with_their_record_and_the_papers_split():
    assert TRAINED.is_file() and TRAINED.stat().st_size < 200_000
    record = torch.load(TRAINED, map_location="cpu", weights_only=False)["record"]
    paper = torch.load(PAPER_WEIGHTS, map_location="cpu", weights_only=False)["record"]
    assert record["train"] == paper["train"] and record["test"] == paper["test"]  # no test pose seen
    assert record["history"][-1]["test_correlation"] > 0.5
    assert not load_detail_net().training


def test_the_shipped_numpy_weights_are_the_trained_network_and_predict_as_it_does(tmp_path):
    """The default runs on detail.npz without torch: it must hold detail.pt's weights, and its float32 numpy
    forward pass must agree with the torch network's (to float32 round-off: 1e-4 relative)."""
    export_weights(load_detail_net(), tmp_path / "again.npz")
    shipped, again = np.load(DETAIL_WEIGHTS), np.load(tmp_path / "again.npz")
    assert sorted(shipped.files) == sorted(again.files)
    for name in shipped.files:
        np.testing.assert_array_equal(shipped[name], again[name], err_msg=name)
    features = descriptors(edge_pole_plane(4)[0], 2_000)
    with torch.no_grad():
        expected = load_detail_net()(torch.from_numpy(features)).numpy()
    np.testing.assert_allclose(load_detail_weights().predict(features), expected, rtol=1e-4, atol=1e-6)


def test_the_default_method_runs_without_torch(tmp_path):
    """Workers of `learned` (here: the run's own process, for a small scan) never import torch."""
    import subprocess
    import sys

    tile_script = ("import sys, numpy as np; from model import Tile, get_simplifier; "
                   "xyz = np.random.default_rng(0).normal(size=(3000, 3)); "
                   "get_simplifier('learned')(Tile(xyz, np.ones(3000, bool), np.zeros(3), 0), 300); "
                   "print('torch' in sys.modules)")
    result = subprocess.run([sys.executable, "-c", tile_script], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0 and result.stdout.strip() == "False", result.stderr


def test_training_on_generated_meshes_writes_weights_that_predict(tmp_path):
    """A tiny run of the real training loop (two poses of three shapes) through the CLI command."""
    import trimesh
    from click.testing import CliRunner

    from pipeline.apps.cli import cli

    shapes = {"ball": trimesh.creation.icosphere(3), "box": trimesh.creation.box((1, 2, 3)),
              "can": trimesh.creation.cylinder(0.5, 2, sections=48)}
    for name, mesh in shapes.items():
        for pose in range(2):
            mesh.apply_transform(trimesh.transformations.rotation_matrix(0.4 * pose, [0, 1, 0]))
            mesh.export(tmp_path / f"{name}{pose}.off")
    out = tmp_path / "detail.pt"
    result = CliRunner().invoke(cli, ["train-detail", "--data", str(tmp_path), "--out", str(out), "--epochs", "2",
                                      "--views", "1"])
    assert result.exit_code == 0, result.output
    record = torch.load(out, map_location="cpu", weights_only=False)["record"]
    assert len(record["train"]) == 3 and len(record["test"]) == 3 and len(record["history"]) == 2
    tile, _, _ = edge_pole_plane(4)
    from model.detail import predicted_loss

    loss = predicted_loss(tile, 2_000, out.with_suffix(".npz"))  # the numpy weights written beside the .pt
    assert loss.shape == (len(tile.xyz),) and np.isfinite(loss).all() and (loss >= 0).all()
