"""Coarse copies (:func:`zernet.geometry.coarsen_surface`): about the vertex count asked for, the same surface
(area, position), every original vertex sent to a copy vertex close to it; clouds sampled evenly."""

from __future__ import annotations

import numpy as np
from meshes import icosphere
from scipy.spatial import cKDTree

from zernet.geometry import Surface, coarsen_surface
from zernet.geometry.coarsen import farthest_points


def test_a_mesh_copy_has_about_the_count_asked_for_and_the_same_surface():
    fine = icosphere(5, radius=2.0)  # 10,242 vertices
    copy = coarsen_surface(fine, 1000)
    assert 900 <= copy.surface.n_vertices <= 1100 and not copy.surface.is_point_cloud
    assert abs(copy.surface.area / fine.area - 1) < 0.02
    assert copy.nearest.shape == (fine.n_vertices,) and copy.nearest.max() < copy.surface.n_vertices
    # Each fine vertex lies within about an edge of the copy (edge of 1,000 vertices on area 50: ~0.25).
    distance = np.linalg.norm(copy.surface.vertices[copy.nearest] - fine.vertices, axis=1)
    assert distance.max() < 0.3
    assert np.all(np.abs(np.linalg.norm(copy.surface.vertices, axis=1) - 2.0) < 0.1)


def test_a_cloud_copy_is_an_even_subset_of_its_points():
    points = icosphere(5).vertices
    rng = np.random.default_rng(0)
    dense_cap = points[rng.random(len(points)) < np.where(points[:, 2] > 0.5, 1.0, 0.2)]  # 5x denser on a cap
    cloud = Surface(dense_cap, None, name="cloud")
    copy = coarsen_surface(cloud, 300)
    assert copy.surface.is_point_cloud and copy.surface.n_vertices == 300
    assert np.isin(copy.surface.vertices, dense_cap).all()
    spacing = cKDTree(copy.surface.vertices).query(copy.surface.vertices, k=2)[0][:, 1]
    random_spacing = cKDTree(dense_cap[:300]).query(dense_cap[:300], k=2)[0][:, 1]
    assert spacing.min() > 2 * random_spacing.min()  # farthest points: no two crowded together
    np.testing.assert_array_equal(
        copy.surface.vertices[copy.nearest[farthest_points(dense_cap, 300)]], copy.surface.vertices
    )
