"""Metrics against hand-computed values, and the geodesic error protocol on a sphere."""

import json

import numpy as np
import pytest
import trimesh

from zernet import metrics
from zernet.io_utils import write_json


def test_accuracy_from_labels_and_scores():
    assert metrics.accuracy(np.array([0, 1, 2, 2]), np.array([0, 1, 1, 2])) == pytest.approx(0.75)
    scores = np.array([[0.9, 0.1], [0.2, 0.8], [0.6, 0.4]])
    assert metrics.accuracy(scores, np.array([0, 1, 1])) == pytest.approx(2 / 3)


def test_segmentation_scores_hand_computed():
    target = np.array([0, 0, 0, 1, 1, 2])
    pred = np.array([0, 0, 1, 1, 2, 2])
    s = metrics.segmentation_scores(pred, target, num_classes=4)
    assert s["accuracy"] == pytest.approx(4 / 6)
    # class 0: 2/3 recall; class 1: 1/2; class 2: 1/1; class 3 absent -> NaN, excluded from the mean.
    assert s["per_class_accuracy"][:3] == pytest.approx([2 / 3, 1 / 2, 1.0])
    assert np.isnan(s["per_class_accuracy"][3])
    assert s["mean_class_accuracy"] == pytest.approx((2 / 3 + 1 / 2 + 1) / 3)
    # IoU: class 0 2/(3+2-2)=2/3; class 1 1/(2+2-1)=1/3; class 2 1/(1+2-1)=1/2.
    assert s["per_class_iou"][:3] == pytest.approx([2 / 3, 1 / 3, 1 / 2])
    assert s["mean_iou"] == pytest.approx((2 / 3 + 1 / 3 + 1 / 2) / 3)
    pooled = metrics.confusion_matrix(pred, target, 4) + metrics.confusion_matrix(target, target, 4)
    assert metrics.segmentation_scores(confusion=pooled)["accuracy"] == pytest.approx(10 / 12)


def test_regression_scores_hand_computed():
    t = np.array([1.0, 2.0, 4.0, 5.0])
    p = np.array([1.1, 1.5, 4.0, 6.5])
    s = metrics.regression_scores(p, t)
    rel = np.array([0.1, 0.25, 0.0, 0.3])
    assert s["MAPE"] == pytest.approx(rel.mean())
    assert s["RRMSE"] == pytest.approx(np.sqrt(np.mean((p - t) ** 2)) / np.sqrt(np.mean(t**2)))
    assert s["PCC"] == pytest.approx(np.corrcoef(p, t)[0, 1])
    assert s["HR10"] == pytest.approx(0.5)  # 0.1 (boundary counts) and 0.0
    assert s["HR20"] == pytest.approx(0.5)
    assert s["HR30"] == pytest.approx(1.0)
    perfect = metrics.regression_scores(t, t)
    assert perfect["MAPE"] == 0 and perfect["RRMSE"] == 0 and perfect["PCC"] == pytest.approx(1.0)


def test_aggregate_scores():
    agg = metrics.aggregate_scores({"a": {"MAPE": 0.1, "PCC": 0.9, "curve": [1, 2]}, "b": {"MAPE": 0.3, "PCC": 0.7}})
    assert agg["mean"]["MAPE"] == pytest.approx(0.2) and agg["mean"]["PCC"] == pytest.approx(0.8)
    assert "curve" not in agg["mean"] and agg["n"] == 2


@pytest.fixture(scope="module")
def sphere():
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=2.0)
    return np.asarray(mesh.vertices), np.asarray(mesh.faces)


def test_sphere_diameter_is_pi_r(sphere):
    vertices, faces = sphere
    assert metrics.geodesic_diameter(vertices, faces) == pytest.approx(np.pi * 2.0, rel=0.01)


def test_geodesic_errors_zero_for_perfect_and_exact_for_neighbours(sphere):
    vertices, faces = sphere
    n = len(vertices)
    truth = np.arange(n)
    assert np.all(metrics.geodesic_errors(vertices, truth, truth, faces=faces, diameter=1.0) == 0)
    # Predict an antipodal vertex: the error is half the circumference = the diameter.
    antipode = np.argmin(vertices @ vertices[0])
    pred = truth.copy()
    pred[0] = antipode
    errors = metrics.geodesic_errors(vertices, pred, truth, faces=faces, diameter=np.pi * 2.0)
    assert errors[0] == pytest.approx(1.0, rel=0.01) and np.all(errors[1:] == 0)
    # A neighbouring vertex: the geodesic is the great-circle arc, close to the chord.
    neighbour = faces[faces[:, 0] == 5][0, 1]
    pred[0] = truth[0]
    pred[5] = neighbour
    arc = 2.0 * np.arccos(np.clip(vertices[5] @ vertices[neighbour] / 4.0, -1, 1))
    errors = metrics.geodesic_errors(vertices, pred, truth, faces=faces, diameter=1.0)
    assert errors[5] == pytest.approx(arc, rel=0.02)


def test_error_curve_monotone_and_endpoints():
    errors = np.array([0.0, 0.0, 0.01, 0.05, 0.2, np.inf])
    radii, frac = metrics.error_curve(errors)
    assert radii[0] == 0 and radii[-1] == pytest.approx(0.1) and len(radii) == 101
    assert np.all(np.diff(frac) >= 0)
    assert frac[0] == pytest.approx(2 / 6) and frac[-1] == pytest.approx(4 / 6)
    scores = metrics.correspondence_scores([errors[:3], errors[3:]])
    assert scores["accuracy"] == pytest.approx(2 / 6) and scores["within_0.05"] == pytest.approx(4 / 6)


def test_metrics_files_are_strict_json_with_null_for_undefined_scores(tmp_path):
    scores = metrics.segmentation_scores(np.array([0, 0, 1]), np.array([0, 0, 1]), num_classes=4)
    assert np.isnan(scores["per_class_accuracy"][2])
    path = write_json(
        tmp_path / "m.json",
        {
            "summary": scores,
            "inf": float("inf"),
            "n": np.int64(3),
            "array": np.array([1.5, np.nan]),
            "flag": np.bool_(True),
        },
    )

    def refuse(constant):
        raise ValueError(f"not JSON: {constant}")

    loaded = json.loads(path.read_text(), parse_constant=refuse)
    assert loaded["summary"]["per_class_accuracy"] == [1.0, 1.0, None, None]
    assert loaded["inf"] is None and loaded["n"] == 3 and loaded["array"] == [1.5, None] and loaded["flag"] is True
    with pytest.raises(TypeError, match="not JSON serialisable: object"):
        write_json(tmp_path / "bad.json", {"x": object()})


def test_geodesic_errors_of_one_mesh_measure_each_pair_once(sphere, monkeypatch):
    vertices, faces = sphere
    n = len(vertices)
    rng = np.random.default_rng(4)
    truth = np.arange(n)
    first, second = truth.copy(), truth.copy()
    first[:20] = rng.integers(0, n, 20)
    second[10:30] = rng.integers(0, n, 20)
    second[10:20] = first[10:20]  # pairs both predictions share are measured once
    errors = metrics.GeodesicErrors(vertices, faces)
    calls = []
    pair = metrics._Geodesics.pair
    monkeypatch.setattr(metrics._Geodesics, "pair", lambda self, a, b: calls.append((a, b)) or pair(self, a, b))
    got = [errors(first, truth), errors(second, truth)]
    distinct = {(int(t), int(p)) for prediction in (first, second) for t, p in zip(truth, prediction) if t != p}
    assert sorted(calls) == sorted(distinct)
    for prediction, values in zip((first, second), got):  # the same numbers as one call each
        np.testing.assert_array_equal(
            values, metrics.geodesic_errors(vertices, prediction, truth, faces=faces, diameter=errors.diameter)
        )
