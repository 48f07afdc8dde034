"""Membrane stress under inner pressure (zernet.geometry.membrane): Laplace's law on spheres and cylinders, invariances,
errors, cache; and the "membrane" feature part built on it."""

import numpy as np
import pytest
import trimesh
from meshes import grid, icosphere, open_cylinder
from scipy.spatial.transform import Rotation

from zernet.data.dataset import DatasetError
from zernet.data.features import compute_features, feature_channels, feature_parts
from zernet.geometry import Surface, SurfaceError, membrane_stress

NU = 0.45


def _sphere(radius=2.0, subdivisions=3):
    return icosphere(subdivisions, radius)


@pytest.mark.parametrize("prestress", [0.0, 0.1])
def test_closed_sphere_follows_laplace_law(prestress):
    radius = 2.0
    stress = membrane_stress(_sphere(radius), prestress, NU)
    # Equal biaxial σ = pR/2t (its von Mises value is σ itself); the prestress carries a share of the load.
    expected = radius / 2 / (1 + prestress / (1 + NU))
    assert np.median(stress) == pytest.approx(expected, rel=0.005)
    np.testing.assert_allclose(stress, expected, rtol=0.06)


@pytest.mark.parametrize("prestress", [0.0, 0.05])
def test_long_clamped_cylinder_hoop_stress(prestress):
    radius = 1.0
    cylinder = open_cylinder(radius=radius, height=12.0, around=48, along=73)
    stress = membrane_stress(cylinder, prestress, NU)
    middle = np.abs(cylinder.vertices[:, 2]) < 1.0
    # Hoop σ = pR/t(1 + τ); clamped ends hold the axial strain at zero, so σ_axial = ν σ_hoop.
    hoop = radius / (1 + prestress)
    np.testing.assert_allclose(stress[middle], hoop * np.sqrt(1 - NU + NU**2), rtol=0.005)


def test_invariant_under_rigid_motion_reindexing_and_orientation_and_linear_in_size():
    mesh = trimesh.creation.capsule(height=2.0, radius=0.8, count=[16, 16])
    surface = Surface(mesh.vertices, mesh.faces, name="capsule")
    reference = membrane_stress(surface, 0.02)
    rotation = Rotation.from_euler("xyz", [0.3, -1.1, 2.0]).as_matrix()
    permutation = np.random.default_rng(0).permutation(surface.n_vertices)
    inverse = np.argsort(permutation)
    moved = Surface((surface.vertices @ rotation.T + [5.0, -2.0, 1.0])[permutation], inverse[surface.faces])
    np.testing.assert_allclose(membrane_stress(moved, 0.02), reference[permutation], rtol=1e-6)
    # Flipped normals: the pressure acts from the other side, every stress changes sign, von Mises does not.
    flipped = Surface(surface.vertices, surface.faces[:, ::-1])
    np.testing.assert_allclose(membrane_stress(flipped, 0.02), reference, rtol=1e-6)
    # σ ~ pR/t: a surface three times larger carries three times the stress.
    larger = Surface(surface.vertices * 3.0, surface.faces)
    np.testing.assert_allclose(membrane_stress(larger, 0.02), 3.0 * reference, rtol=1e-6)


def test_unused_vertex_and_a_second_closed_part_change_nothing():
    sphere = _sphere(subdivisions=2)
    cylinder = open_cylinder(radius=1.0, height=4.0, around=24, along=13)
    alone = membrane_stress(cylinder, 0.02)
    # One surface of an open cylinder, a closed sphere far away and a stray vertex no face uses.
    vertices = np.concatenate([cylinder.vertices, sphere.vertices + [10.0, 0.0, 0.0], [[0.0, 0.0, 50.0]]])
    faces = np.concatenate([cylinder.faces, sphere.faces + cylinder.n_vertices])
    both = membrane_stress(Surface(vertices, faces, name="parts"), 0.02)
    np.testing.assert_allclose(both[: cylinder.n_vertices], alone, rtol=1e-6)
    np.testing.assert_allclose(both[cylinder.n_vertices : -1], membrane_stress(sphere, 0.02), rtol=1e-6)
    assert both[-1] == 0.0


def test_errors_name_the_surface():
    flat = grid(6)
    with pytest.raises(SurfaceError, match="grid.*singular.*prestress"):
        membrane_stress(flat, 0.0)
    with pytest.raises(SurfaceError, match="cloud.*triangle mesh"):
        membrane_stress(Surface(flat.vertices, name="cloud"))
    midpoint = (flat.vertices[0] + flat.vertices[1]) / 2  # a face through it and its edge has no area
    degenerate = Surface(
        np.concatenate([flat.vertices, [midpoint]]),
        np.concatenate([flat.faces, [[0, 1, flat.n_vertices]]]),
        name="sliver",
    )
    with pytest.raises(SurfaceError, match=f"sliver: face {flat.n_faces} has zero area"):
        membrane_stress(degenerate, 0.02)
    with pytest.raises(ValueError, match="poisson_ratio"):
        membrane_stress(flat, 0.02, poisson_ratio=0.5)
    # With a prestress the clamped flat plate is well posed: pressure bulges it.
    assert np.all(np.isfinite(membrane_stress(flat, 0.02)))


def test_cache_round_trip_and_recovers_from_a_damaged_file(tmp_path):
    surface = _sphere(subdivisions=2)
    first = membrane_stress(surface, 0.02, cache_dir=tmp_path)
    files = list((tmp_path / "membrane").glob("*.npy"))
    assert len(files) == 1
    np.save(files[0], np.zeros(surface.n_vertices))  # a cached value is what is returned
    np.testing.assert_array_equal(membrane_stress(surface, 0.02, cache_dir=tmp_path), 0.0)
    files[0].write_bytes(b"truncated")  # an unreadable file is recomputed and replaced
    np.testing.assert_array_equal(membrane_stress(surface, 0.02, cache_dir=tmp_path), first)
    np.testing.assert_array_equal(np.load(files[0]), first)
    # Other parameters, other entry.
    membrane_stress(surface, 0.04, cache_dir=tmp_path)
    assert len(list((tmp_path / "membrane").glob("*.npy"))) == 2


def test_membrane_feature_part():
    surface = _sphere(radius=2.0, subdivisions=2)
    features = compute_features(surface, "xyz+membrane")
    assert features.shape == (surface.n_vertices, feature_channels("xyz+membrane")) == (surface.n_vertices, 6)
    # The log of the sphere's uniform stress at each prestress, decreasing with the prestress.
    medians = np.median(features[:, 3:], axis=0)
    assert np.all(np.diff(medians) < 0)
    assert medians[0] == pytest.approx(np.log(1.0 / (1 + 0.01 / (1 + NU))), abs=0.01)
    with pytest.raises(DatasetError, match="cloud.*triangle mesh"):
        compute_features(Surface(surface.vertices, name="cloud"), "membrane")


def test_feature_kinds_are_plus_joined_parts():
    assert feature_parts("shape+curvature+membrane") == ["shape", "curvature", "membrane"]
    assert feature_channels("xyz+normals") == 6
    for bad in ("xyz+xyz", "xyz+colour", "", "shape+"):
        with pytest.raises(DatasetError, match="unknown feature kind"):
            feature_parts(bad)
