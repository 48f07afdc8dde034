"""Geodesic soft labels (``train.label_radius``): the template's neighbourhoods, the target distribution, the
loss it gives, and a correspondence run that trains with it (and a run without a template that refuses it)."""

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from meshes import grid_mesh
from tiny_configs import faust_run_config, tiny_config

from zernet.inference import load_checkpoint
from zernet.inference.template_graph import edge_graph, edge_neighbourhoods, geodesic_soft_labels
from zernet.training import train
from zernet.training.config import ConfigError, TrainSection
from zernet.training.losses import compute_loss


def test_edge_distances_on_a_grid_are_the_manhattan_path_along_the_edges():
    vertices, faces = grid_mesh(7)  # spacing 1; the diagonals run from (i, j) to (i + 1, j + 1)
    found = edge_neighbourhoods(edge_graph(vertices, faces), limit=2.0)
    centre = 24  # the middle of the 7 x 7 grid
    near, distances = found[centre]
    by_vertex = dict(zip(near.tolist(), distances.tolist()))
    assert by_vertex[centre] == 0.0
    assert by_vertex[centre + 1] == pytest.approx(1.0) and by_vertex[centre + 7] == pytest.approx(1.0)
    assert by_vertex[centre + 2] == pytest.approx(2.0)
    assert by_vertex[centre + 8] == pytest.approx(np.sqrt(2))  # along a diagonal edge
    assert centre + 3 not in by_vertex and max(distances) <= 2.0


def test_the_target_is_a_normalised_gaussian_of_the_distance_peaked_at_the_true_vertex():
    vertices, faces = grid_mesh(9)
    diameter = 10.0
    indices, weights = geodesic_soft_labels(vertices, faces, radius=0.2, diameter=diameter)  # within 2 edges
    assert indices.shape == weights.shape and indices.dtype == torch.int64 and weights.dtype == torch.float32
    torch.testing.assert_close(weights.sum(dim=1), torch.ones(len(vertices)))
    rows = torch.arange(len(vertices))
    # the true vertex carries the largest weight, so the hard label is the target's argmax
    assert torch.equal(indices[rows, weights.argmax(dim=1)], rows)
    centre = 40
    row = dict(zip(indices[centre].tolist(), weights[centre].tolist()))
    sigma = 0.2 * diameter / 2
    assert row[centre + 1] / row[centre] == pytest.approx(np.exp(-0.5 / sigma**2), rel=1e-5)
    assert row[centre + 2] / row[centre] == pytest.approx(np.exp(-0.5 * 4 / sigma**2), rel=1e-5)
    assert (weights > 0).sum(dim=1).max() < len(vertices)  # cut at the radius: no vertex sees the whole grid


def test_the_soft_cross_entropy_is_the_dense_one_and_the_hard_one_at_a_vanishing_radius():
    vertices, faces = grid_mesh(5)
    n = len(vertices)
    generator = torch.Generator().manual_seed(0)
    output = torch.randn(40, n, generator=generator, dtype=torch.float64, requires_grad=True)
    target = torch.randint(0, n, (40,), generator=generator)
    indices, weights = geodesic_soft_labels(vertices, faces, radius=0.5, diameter=4.0)
    dense = torch.zeros(n, n, dtype=torch.float64).scatter_add_(1, indices, weights.double())
    expected = -(dense[target] * F.log_softmax(output, dim=1)).sum(dim=1).mean()
    soft = (indices, weights.double())
    torch.testing.assert_close(compute_loss("cross_entropy", output, target, soft_labels=soft), expected)
    assert torch.autograd.gradcheck(
        lambda o: compute_loss("cross_entropy", o, target, soft_labels=soft), (output,), eps=1e-6
    )
    alone = geodesic_soft_labels(vertices, faces, radius=0.1, diameter=4.0)  # 0.4 < one edge: itself only
    torch.testing.assert_close(
        compute_loss("cross_entropy", output.float(), target, soft_labels=alone),
        F.cross_entropy(output.float(), target),
    )


def test_the_radius_is_a_fraction_of_the_diameter():
    assert TrainSection(label_radius=0.02).label_radius == 0.02
    for bad in (-0.1, 1.0, "wide"):
        with pytest.raises(ConfigError, match="train.label_radius"):
            TrainSection(label_radius=bad)


def test_a_correspondence_run_trains_on_soft_labels_and_a_run_without_a_template_refuses_them(
    ellipsoid_faust_root, cache_dir, tmp_path
):
    config = faust_run_config(
        ellipsoid_faust_root,
        642,
        {"r0": 1.2, "n_samples": 1500, "patch_size": 30, "n_max": 2},
        train={"epochs": 2, "label_radius": 0.05},
        eval={"refine_rings": [0]},
    )
    train(config, tmp_path / "soft", progress=False)
    history = load_checkpoint(tmp_path / "soft" / "last.pt")["state"]["history"]
    log = (tmp_path / "soft" / "train.log").read_text()
    assert "soft labels: each target spread over the template vertices within 0.05" in log
    assert all(np.isfinite(entry["train_loss"]) for entry in history) and len(history) == 2
    with pytest.raises(ConfigError, match="train.label_radius .* no template mesh"):
        train(tiny_config(cache_dir, label_radius=0.05), tmp_path / "synthetic", progress=False)
