"""Rotation-invariant shape descriptors computed with the patch operator (zernet.data.features)."""

import subprocess
import sys

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from zernet.data.features import (
    BOUNDARY_SATURATION,
    compute_features,
    curvature_descriptors,
    feature_channels,
    shape_descriptors,
)
from zernet.geometry import Surface
from zernet.operators import PatchConfig, build_patch_operator
from zernet.zernike import index_to_nm, orders

# patch_size large enough that every patch covers its whole disk, so the fit sees the analytic field.
CONFIG = PatchConfig(r0=0.5, n_samples=6000, patch_size=200, n_max=4, seed=0)


def _sphere(radius=2.0):
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=radius)
    return Surface(mesh.vertices, mesh.faces, name="sphere")


def _columns(n_max):
    keys = sorted(index_to_nm(j) for j, m in enumerate(orders(n_max)) if m >= 0)
    return {key: i for i, key in enumerate(keys)}


def test_sphere_descriptors_match_curvature():
    radius = 2.0
    surface = _sphere(radius)
    operator = build_patch_operator(surface, CONFIG)
    features = shape_descriptors(surface, operator)
    assert features.shape == (surface.n_vertices, feature_channels("shape", CONFIG.n_max))
    columns = _columns(CONFIG.n_max)
    # Height above the tangent plane of a sphere: h ≈ -ρ²/(2R), ρ = r0·r. Its Zernike expansion has only
    # m = 0 terms: h = -(r0²/2R) r² and r² = (Z_0^0 + Z_2^0/√3)·√π/2, so a_2^0 = -(r0²/2R)·√π/(2√3).
    expected = -(CONFIG.r0**2 / (2 * radius)) * np.sqrt(np.pi) / (2 * np.sqrt(3)) / CONFIG.r0
    assert np.median(features[:, columns[(2, 0)]]) == pytest.approx(expected, rel=0.1)
    # No anisotropy on a sphere: |Z_2^±2| small against the defocus term.
    assert np.median(features[:, columns[(2, 2)]]) < 0.1 * abs(expected)
    # Closed surface: boundary channel saturated.
    assert np.all(features[:, -1] == BOUNDARY_SATURATION)


def test_descriptors_invariant_under_rigid_motion():
    surface = _sphere()
    mesh = trimesh.creation.capsule(height=2.0, radius=0.8, count=[24, 24])
    surface = Surface(mesh.vertices, mesh.faces, name="capsule")
    rotation = Rotation.from_euler("xyz", [0.3, -1.1, 2.0]).as_matrix()
    moved = Surface(surface.vertices @ rotation.T + np.array([5.0, -2.0, 1.0]), surface.faces, name="moved")
    a = shape_descriptors(surface, build_patch_operator(surface, CONFIG))
    b = shape_descriptors(moved, build_patch_operator(moved, CONFIG))
    # Sampling is seeded in the surface's own barycentric terms, so both fits see the same samples; the
    # front backend's distances differ by rounding, which can move a sample at r ≈ r0 in or out of a patch.
    np.testing.assert_allclose(a, b, atol=2e-5)


def test_boundary_distance_channel_on_open_plane():
    n = 21
    x, y = np.meshgrid(np.linspace(0, 4, n), np.linspace(0, 4, n))
    vertices = np.stack([x.ravel(), y.ravel(), np.zeros(n * n)], axis=1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    surface = Surface(vertices, faces, name="plane")
    features = compute_features(surface, "shape", [build_patch_operator(surface, CONFIG)])
    distance = np.minimum(vertices[:, 0], 4 - vertices[:, 0])
    distance = np.minimum(distance, np.minimum(vertices[:, 1], 4 - vertices[:, 1]))
    np.testing.assert_allclose(features[:, -1], np.minimum(distance / CONFIG.r0, BOUNDARY_SATURATION), atol=1e-6)
    # A plane has zero height everywhere: every descriptor vanishes.
    assert np.abs(features[:, :-1]).max() < 1e-8


def test_curvature_descriptors_on_sphere_and_channel_count():
    radius = 2.0
    surface = _sphere(radius)
    radii = [0.5, 1.0, 3.0]
    features = curvature_descriptors(surface, radii)
    # Every column is H·r with H = 1/R everywhere: r0/R for the vertex column, r/R for each ball.
    expected = np.array([radii[0]] + radii) / radius
    # The 12 valence-5 vertices of an icosphere carry a known ~15 % bias of the per-vertex cotan estimate
    # (barycentric areas); the balls average it away.
    assert np.median(features[:, 0]) == pytest.approx(expected[0], rel=0.02)
    np.testing.assert_allclose(features[:, 1:], np.broadcast_to(expected[1:], (len(features), 3)), rtol=0.03)
    operator = build_patch_operator(surface, CONFIG)
    full = compute_features(surface, "shape+curvature", [operator])
    assert (
        full.shape[1]
        == feature_channels("shape+curvature", CONFIG.n_max)
        == feature_channels("shape", CONFIG.n_max) + 2
    )
    np.testing.assert_array_equal(full[:, :-2], compute_features(surface, "shape", [operator]))


def test_curvature_descriptors_invariant_under_rigid_motion_and_reindexing():
    mesh = trimesh.creation.capsule(height=2.0, radius=0.8, count=[24, 24])
    surface = Surface(mesh.vertices, mesh.faces, name="capsule")
    rotation = Rotation.from_euler("xyz", [0.3, -1.1, 2.0]).as_matrix()
    permutation = np.random.default_rng(0).permutation(surface.n_vertices)
    inverse = np.argsort(permutation)
    moved = Surface(
        (surface.vertices @ rotation.T + [5.0, -2.0, 1.0])[permutation], inverse[surface.faces], name="moved"
    )
    a = curvature_descriptors(surface, [0.43, 1.07])
    b = curvature_descriptors(moved, [0.43, 1.07])
    np.testing.assert_allclose(b, a[permutation], atol=1e-5)
    # Ball memberships are exact only off the mesh's lattice distances, hence the odd radii. The cylinder part
    # has H = 1/(2·0.8), the hemispherical caps 1/0.8: the small ball sees the cylinder value.
    middle = np.abs(surface.vertices[:, 2]) < 0.5
    np.testing.assert_allclose(a[middle, 1], 0.43 / 1.6, rtol=0.05)


def _ellipsoid(subdivisions=3):
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    return Surface(mesh.vertices * [1.0, 1.0, 3.0], mesh.faces, name="ellipsoid")


def test_heat_kernel_descriptors_are_constant_on_a_sphere():
    # Every point of a sphere is alike: each column is its own area-weighted mean, 1.
    hks = compute_features(_sphere(), "hks")
    assert hks.shape == (_sphere().n_vertices, feature_channels("hks"))
    np.testing.assert_allclose(hks, 1.0, rtol=0.02)


def test_heat_kernel_descriptors_keep_more_heat_at_the_tips_of_an_ellipsoid():
    surface = _ellipsoid()
    hks = compute_features(surface, "hks")
    tips = np.abs(surface.vertices[:, 2]) > 2.9
    equator = np.abs(surface.vertices[:, 2]) < 0.2
    # The poles of a 1 x 1 x 3 ellipsoid (Gauss curvature 9 against 1/9) hold more heat than the waist at
    # every time but the last, where the heat has spread evenly (the constant 1); most at the middle times.
    at_tips, at_equator = hks[tips].mean(axis=0), hks[equator].mean(axis=0)
    assert (at_tips[:15] > at_equator[:15]).all()
    assert (at_tips[4:9] > 1.5 * at_equator[4:9]).all()


def test_heat_kernel_descriptors_invariant_under_similarity_and_reindexing():
    surface = _ellipsoid()
    rotation = Rotation.from_euler("xyz", [0.3, -1.1, 2.0]).as_matrix()
    permutation = np.random.default_rng(0).permutation(surface.n_vertices)
    moved = Surface(
        (2.5 * surface.vertices @ rotation.T + [5.0, -2.0, 1.0])[permutation],
        np.argsort(permutation)[surface.faces],
        name="moved",
    )
    np.testing.assert_allclose(compute_features(moved, "hks"), compute_features(surface, "hks")[permutation], rtol=1e-3)


def test_heat_kernel_descriptors_of_a_cloud_follow_its_mesh():
    surface = _ellipsoid(subdivisions=4)
    cloud = Surface(surface.vertices, None, name="cloud")
    on_mesh, on_cloud = np.log(compute_features(surface, "hks")), np.log(compute_features(cloud, "hks"))
    for column in (2, 6, 10):
        assert np.corrcoef(on_mesh[:, column], on_cloud[:, column])[0, 1] > 0.95


def test_a_registered_input_part_joins_every_feature_kind_function(monkeypatch):
    from zernet.data import features

    monkeypatch.setattr(features, "FEATURE_PARTS", dict(features.FEATURE_PARTS))
    features.register_input_part("height", 1, lambda surface, operators, cache_dir: surface.vertices[:, 1:2])
    sphere = _sphere()
    values = compute_features(sphere, "xyz+height")
    assert values.shape == (sphere.n_vertices, 4) and values.dtype == np.float32
    np.testing.assert_allclose(values[:, 3], sphere.vertices[:, 1], rtol=1e-6)
    assert feature_channels("shape+height", [4]) == feature_channels("shape", [4]) + 1
    assert features.feature_slices("xyz+height+normals", [4]) == {
        "xyz": slice(0, 3),
        "height": slice(3, 4),
        "normals": slice(4, 7),
    }
    assert not features.needs_patch_operators("xyz+height") and features.needs_patch_operators("height+curvature")
    # The same function again is fine (a module reloaded); another one under a taken name is refused.
    with pytest.raises(ValueError, match="'xyz' is already registered by zernet.data.features"):
        features.register_input_part("xyz", 3, _columns)
    with pytest.raises(ValueError, match="no '\\+'"):
        features.register_input_part("a+b", 1, _columns)


def test_the_template_part_is_provided_by_matching_through_its_entry_point():
    # A fresh interpreter that never imports zernet.matching itself: asking for the part loads its provider.
    code = (
        "import sys; from zernet.data.features import feature_channels; "
        "print(feature_channels('xyz+hks+template', 5), 'zernet.matching.template' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == [str(3 + 16 + 3), "True"]


def test_a_broken_or_silent_provider_is_named(monkeypatch):
    from zernet.data import features
    from zernet.data.dataset import DatasetError

    class Entry:
        name, value = "colour", "somepackage.colour"

        def __init__(self, load):
            self.load = load

    def fail():
        raise ImportError("no module named somepackage")

    for load, message in ((fail, "provider somepackage.colour failed to load"), (lambda: None, "did not register")):
        monkeypatch.setattr(features.importlib.metadata, "entry_points", lambda group, load=load: [Entry(load)])
        with pytest.raises(DatasetError, match=message):
            feature_channels("xyz+colour")
    monkeypatch.setattr(features.importlib.metadata, "entry_points", lambda group: [])
    with pytest.raises(DatasetError, match="unknown feature kind 'xyz\\+colour'"):
        feature_channels("xyz+colour")
