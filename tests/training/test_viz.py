"""Renders and plots are written as PNGs of the documented size, without a display."""

import matplotlib.image as mpimg
import numpy as np
import pytest
import trimesh

from zernet import viz
from zernet.metrics import error_curve
from zernet.geometry import Surface


@pytest.fixture(scope="module")
def surface():
    mesh = trimesh.creation.icosphere(subdivisions=2)
    vertices = np.asarray(mesh.vertices) * np.array([1.0, 1.6, 0.8])
    return Surface(vertices, np.asarray(mesh.faces), name="ellipsoid")


def _size(path):
    image = mpimg.imread(path)
    return image.shape[1], image.shape[0]


def test_render_surface_continuous_and_labels(tmp_path, surface):
    path = viz.render_surface(surface, surface.vertices[:, 1], tmp_path / "a.png", title="height", label="y")
    assert path.stat().st_size > 5000 and _size(path) == (1040, 340)
    labels = (surface.vertices[:, 1] > 0).astype(np.int64)
    path = viz.render_surface(surface, labels, tmp_path / "b.png", views=("front", "top"), class_names=["low", "high"])
    assert _size(path) == (720, 340)


def test_render_point_cloud(tmp_path, surface):
    cloud = Surface(surface.vertices, None, surface.vertex_normals(), name="cloud")
    path = viz.render_surface(cloud, surface.vertices[:, 0], tmp_path / "cloud.png", views=("side",))
    assert path.stat().st_size > 2000 and _size(path) == (400, 340)


def test_render_comparison_rows(tmp_path, surface):
    truth = surface.vertices[:, 1]
    prediction = truth + 0.1 * np.sin(5 * surface.vertices[:, 0])
    path = viz.render_comparison(surface, prediction, truth, np.abs(prediction - truth), tmp_path / "c.png",
                                 title="regression")
    assert _size(path) == (1080, 1000)
    labels = (truth > 0).astype(np.int64)
    path = viz.render_comparison(surface, labels[::-1].copy(), labels, None, tmp_path / "d.png")
    assert _size(path) == (1080, 680)
    with pytest.raises(ValueError, match="one value per vertex"):
        viz.render_comparison(surface, truth[:5], truth, None, tmp_path / "e.png")


def test_error_curve_and_training_curves(tmp_path):
    errors = np.abs(np.random.default_rng(0).normal(0, 0.03, 500))
    path = viz.plot_error_curve({"zernet": error_curve(errors), "baseline": error_curve(2 * errors)},
                                tmp_path / "curve.png")
    assert _size(path) == (550, 420)
    history = [{"epoch": e, "train_loss": 2.0 / e, "val_loss": 2.2 / e, "train_accuracy": 1 - 1 / (e + 1),
                "val_accuracy": 1 - 1.2 / (e + 1), "seconds": 1.0} for e in range(1, 21)]
    path = viz.plot_training_curves(history, tmp_path / "history.png")
    assert _size(path) == (1000, 380) and path.stat().st_size > 5000
