"""The matching benchmark's error on a target whose simplifier left faces the exact geodesic solver refuses
(benchmarks/experiments/matching.py: ``errors_on_target``, ``measurable_faces``)."""

import numpy as np
import pytest
from meshes import icosphere

from benchmarks.experiments.matching import errors_on_target, measurable_faces, real_pairs
from zernet.geometry import Surface


def test_faces_sharing_a_directed_edge_or_a_crowded_edge_are_left_out():
    faces = np.array([[0, 1, 2], [2, 1, 3], [0, 1, 4], [1, 0, 5]])
    # 0 -> 1 twice (faces 0 and 2); edge {0, 1} in three faces (0, 2, 3); face 1 is clean.
    np.testing.assert_array_equal(measurable_faces(faces), [False, True, False, False])
    sphere = icosphere(subdivisions=2)
    assert measurable_faces(sphere.faces).all()


def test_a_target_with_a_flipped_duplicate_face_and_a_loose_vertex_is_measured_as_the_clean_one():
    sphere = icosphere(subdivisions=3)
    clean = Surface(sphere.vertices, sphere.faces)
    # A copy of one face with its orientation kept (a directed edge twice) and a vertex in no face.
    vertices = np.vstack([sphere.vertices, sphere.vertices[:1] * 1.0001])
    broken = Surface(vertices, np.vstack([sphere.faces, sphere.faces[:1]]))
    rng = np.random.default_rng(0)
    truth = rng.integers(0, len(sphere.vertices), 200)
    predicted = rng.integers(0, len(sphere.vertices), 200)
    expected, _ = errors_on_target(clean, predicted, truth, 1.0)
    measured, _ = errors_on_target(broken, predicted, truth, 1.0)
    far_from_the_broken_face = ~np.isin(truth, sphere.faces[0]) & ~np.isin(predicted, sphere.faces[0])
    np.testing.assert_allclose(measured[far_from_the_broken_face], expected[far_from_the_broken_face], rtol=0.05)
    # The loose vertex answers through its nearest kept vertex.
    loose = errors_on_target(broken, np.array([len(sphere.vertices)]), np.array([0]), 1.0)[0]
    assert loose[0] < 0.01 * 100


def test_real_pairs_join_two_different_people_and_only_the_people_asked_for():
    every = real_pairs(40)
    assert all(source // 10 != target // 10 for source, target in every)
    assert {scan // 10 for pair in every for scan in pair} <= set(range(8))  # people 8-9 are never read
    held = real_pairs(12, people=(6, 7))
    assert {scan // 10 for pair in held for scan in pair} == {6, 7}
    assert all(source // 10 != target // 10 for source, target in held)
    with pytest.raises(ValueError, match="two different people"):
        real_pairs(2, people=(6,))
