"""Renders and plots are written as PNGs of the documented size, without a display."""

import matplotlib.image as mpimg
import numpy as np
import pytest
import trimesh

from zernet import viz
from zernet.geometry import Surface
from zernet.metrics import error_curve, regression_scores
from zernet.training.run_dir import regression_title


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
    path = viz.render_comparison(
        surface, prediction, truth, np.abs(prediction - truth), tmp_path / "c.png", title="regression"
    )
    assert _size(path) == (1080, 1000)
    labels = (truth > 0).astype(np.int64)
    path = viz.render_comparison(surface, labels[::-1].copy(), labels, None, tmp_path / "d.png")
    assert _size(path) == (1080, 680)
    with pytest.raises(ValueError, match="one value per vertex"):
        viz.render_comparison(surface, truth[:5], truth, None, tmp_path / "e.png")


def test_error_curve_and_training_curves(tmp_path):
    errors = np.abs(np.random.default_rng(0).normal(0, 0.03, 500))
    path = viz.plot_error_curve(
        {"zernet": error_curve(errors), "baseline": error_curve(2 * errors)}, tmp_path / "curve.png"
    )
    assert _size(path) == (550, 420)
    history = [
        {
            "epoch": e,
            "train_loss": 2.0 / e,
            "val_loss": 2.2 / e,
            "train_accuracy": 1 - 1 / (e + 1),
            "val_accuracy": 1 - 1.2 / (e + 1),
            "seconds": 1.0,
        }
        for e in range(1, 21)
    ]
    path = viz.plot_training_curves(history, tmp_path / "history.png")
    assert _size(path) == (1000, 380) and path.stat().st_size > 5000


def _red_pixels(image: np.ndarray, top: float, bottom: float) -> int:
    """Pixels of the right/wrong mask's "wrong" red in a band of rows, left of the colour bars."""
    height, width = image.shape[:2]
    band = image[int(top * height) : int(bottom * height), : int(0.85 * width), :3]
    return int(
        np.count_nonzero(
            (band[..., 0] > 0.45) & (band[..., 1] < 0.2) & (band[..., 2] < 0.2) & (band[..., 0] > 2.5 * band[..., 1])
        )
    )


def test_corner_cells_tile_each_triangle_and_belong_to_its_corners():
    triangles = np.random.default_rng(0).normal(size=(5, 3, 3))
    cells = viz._corner_cells(triangles)
    assert cells.shape == (15, 4, 3)
    np.testing.assert_allclose(cells[0::3, 0], triangles[:, 0])  # cell 3f+i starts at corner i of face f
    np.testing.assert_allclose(cells[2::3, 0], triangles[:, 2])

    def area(polygon):  # planar polygons (each cell lies in its triangle's plane)
        return 0.5 * np.linalg.norm(
            sum(np.cross(polygon[k], polygon[(k + 1) % len(polygon)]) for k in range(len(polygon)))
        )

    for f in range(5):
        np.testing.assert_allclose(sum(area(cells[3 * f + i]) for i in range(3)), area(triangles[f]), rtol=1e-9)


def test_one_wrong_vertex_shows_in_the_prediction_and_in_the_error_row(tmp_path, surface):
    truth = np.zeros(len(surface.vertices), dtype=np.int64)
    front = int(np.argmax(surface.vertices[:, 2]))  # the vertex nearest the camera of the front view
    prediction = truth.copy()
    prediction[front] = 1
    wrong = viz.render_comparison(
        surface,
        prediction,
        truth,
        prediction != truth,
        tmp_path / "wrong.png",
        views=("front",),
        error_label="wrong label",
        class_names=["a", "b"],
    )
    right = viz.render_comparison(
        surface,
        truth,
        truth,
        truth != truth,
        tmp_path / "right.png",
        views=("front",),
        error_label="wrong label",
        class_names=["a", "b"],
    )
    wrong_image, right_image = mpimg.imread(wrong), mpimg.imread(right)
    assert _red_pixels(right_image, 0.66, 1.0) == 0
    assert _red_pixels(wrong_image, 0.66, 1.0) > 20  # the error row: one vertex's cells, in red
    # The prediction row: the vertex's cells take class 1's colour (tab10 orange) among class 0's blue.
    band = wrong_image[: wrong_image.shape[0] // 3, : int(0.85 * wrong_image.shape[1]), :3]
    orange = (band[..., 0] > 0.6) & (band[..., 1] > 0.3) & (band[..., 1] < 0.6) & (band[..., 2] < 0.2)
    assert np.count_nonzero(orange) > 20


def test_a_boolean_error_gets_a_two_entry_colour_bar(tmp_path, surface, monkeypatch):
    figures = []
    monkeypatch.setattr(viz, "_save", lambda fig, path: figures.append(fig) or path)
    labels = (surface.vertices[:, 1] > 0).astype(np.int64)
    viz.render_comparison(surface, labels, labels, labels == 1, tmp_path / "x.png", class_names=["low", "high"])
    bars = [ax for ax in figures[0].axes if ax.get_label() == "<colorbar>"]
    ticks = [[t.get_text() for t in bar.get_yticklabels()] for bar in bars]
    assert ticks == [["low", "high"], ["low", "high"], ["right", "wrong"]]


def test_training_curves_mark_the_selected_epoch(tmp_path, monkeypatch):
    figures = []
    monkeypatch.setattr(viz, "_save", lambda fig, path: figures.append(fig) or path)
    history = [{"epoch": e, "train_loss": 1.0 / e, "val_accuracy": 0.5 + e / 20} for e in range(1, 6)]
    viz.plot_training_curves(history, tmp_path / "h.png", best_epoch=3)
    for ax in figures[0].axes:
        marks = [line for line in ax.get_lines() if line.get_label() == "selected epoch 3"]
        assert len(marks) == 1 and list(marks[0].get_xdata()) == [3, 3]


def test_regression_title_uses_the_metrics_mape_and_flags_zero_crossing_targets():
    target = np.array([0.0, 1.0, -2.0, 4.0])
    pred = np.array([0.5, 1.5, -2.0, 3.0])
    title = regression_title("s", pred, target)
    assert f"MAPE {regression_scores(pred, target)['MAPE']:.3f}" in title and "inf" not in title
    assert "targets cross zero: relative errors are not meaningful" in title
    assert "touch zero" in regression_title("s", pred, np.abs(target))
    assert regression_title("s", pred, target + 10) == f"s: MAPE {regression_scores(pred, target + 10)['MAPE']:.3f}"
