"""The patch fit of issue 15: every sample within r0 by default (the paper's 50 nearest selectable), a
ridge that spares the piston and so fits a constant field exactly on every patch, linear fields reproduced on a
plane, and cached operators of another backend version or format rebuilt rather than reused."""

import numpy as np
import pytest
import trimesh
from meshes import grid_mesh

from zernet.geometry import BACKEND_VERSIONS, Surface, compute_polar, mesh_from_cloud, sample_surface
from zernet.operators import PatchConfig, build_patch_operator, cache_key
from zernet.operators.fit import fit_patches, ridge_weights
from zernet.zernike import num_bases, zernike_basis


def bumpy_sphere(seed=0):
    mesh = trimesh.creation.icosphere(2, radius=4.0)
    rng = np.random.default_rng(seed)
    return Surface(mesh.vertices * (1 + 0.03 * rng.standard_normal((len(mesh.vertices), 1))), mesh.faces, name="bumpy")


def test_ridge_weights_spare_the_piston_only():
    weights = ridge_weights(5)
    assert weights.shape == (num_bases(5),)
    assert weights[0] == 0.0
    np.testing.assert_array_equal(weights[1:], 1.0)


@pytest.mark.parametrize("patch_size", [None, 50, 12])
def test_constant_field_gives_the_exact_piston_and_nothing_else(patch_size):
    # Whatever the coverage (all samples, the 50 nearest, 12 < k samples): a = √π e_0 exactly.
    surface = bumpy_sphere()
    op = build_patch_operator(surface, PatchConfig(r0=2.0, n_samples=1500, patch_size=patch_size, ridge=1e-2))
    coefficients = (op.matrix @ np.full(surface.n_vertices, 3.0)).reshape(-1, op.k)
    np.testing.assert_allclose(coefficients[:, 0], 3.0 * np.sqrt(np.pi), rtol=1e-9)
    assert np.abs(coefficients[:, 1:]).max() < 1e-9


def test_grouped_fit_equals_the_padded_closed_form():
    rng = np.random.default_rng(0)
    counts = np.array([30, 7, 30, 0, 45])
    radius, angle = rng.uniform(0, 1, (5, 45)), rng.uniform(-np.pi, np.pi, (5, 45))
    fit, lam = fit_patches(radius, angle, counts, 3, 1e-2)
    weights = ridge_weights(3)
    for p, n in enumerate(counts):
        assert np.all(fit[p, :, n:] == 0.0)
        if n:
            basis = zernike_basis(radius[p, :n], angle[p, :n], 3)
            expected = np.linalg.solve(basis.T @ basis + lam * np.diag(weights), basis.T)
            np.testing.assert_allclose(fit[p, :, :n], expected, atol=1e-12)


@pytest.mark.parametrize("ridge", [1e-3, 1e-6])
def test_linear_field_is_reproduced_on_a_plane(ridge):
    vertices, faces = grid_mesh(41, spacing=0.25, jitter=0.2, seed=1)
    plane = Surface(vertices, faces)
    op = build_patch_operator(plane, PatchConfig(r0=1.0, n_samples=6000, ridge=ridge))
    samples = sample_surface(plane, 6000, seed=0)
    field = vertices @ np.array([0.6, -0.8, 0.0]) + 2.0
    interior = np.flatnonzero(np.abs(vertices[:, :2]).max(axis=1) < 5.0 - 1.2)
    coefficients = (op.matrix @ field).reshape(-1, op.k)[interior]
    index = op.patch_sample_index[interior]
    values = (samples.interpolation @ field)[np.maximum(index, 0)]
    fitted = np.einsum("vnk,vk->vn", op.patch_basis[interior], coefficients)
    residual = np.where(index >= 0, fitted - values, 0.0)
    variation = np.where(index >= 0, values - field[interior, None], 0.0)
    relative = np.linalg.norm(residual, axis=1) / np.linalg.norm(variation, axis=1)
    # A linear field is degree 1 in the disk: all that remains is the ridge, a relative bias of about `ridge`.
    assert np.median(relative) < 2 * max(ridge, 1e-5) and relative.max() < 5 * max(ridge, 1e-5)


def test_patch_size_none_takes_every_sample_within_r0_and_50_the_nearest():
    surface = bumpy_sphere()
    samples = sample_surface(surface, 3000, seed=0)
    polar = compute_polar(surface, samples, 2.0)
    full = build_patch_operator(surface, PatchConfig(r0=2.0, n_samples=3000))
    np.testing.assert_array_equal((full.patch_sample_index >= 0).sum(axis=1), polar.counts())
    assert polar.counts().min() > 50
    paper = build_patch_operator(surface, PatchConfig(r0=2.0, n_samples=3000, patch_size=50))
    assert paper.patch_sample_index.shape[1] == 50 and np.all(paper.patch_sample_index >= 0)
    np.testing.assert_array_equal(paper.patch_sample_index, full.patch_sample_index[:, :50])  # the nearest 50


def test_default_backend_is_front_for_meshes_and_point_clouds(tmp_path):
    surface = bumpy_sphere()
    config = PatchConfig(r0=2.0, n_samples=800)
    assert cache_key(surface, config) == cache_key(surface, PatchConfig(r0=2.0, n_samples=800), "front")
    # A cloud goes through the front on its triangulation: the same operator as that mesh's, cached under it.
    cloud = Surface(surface.vertices, None, name="cloud")
    op = build_patch_operator(cloud, config, cache_dir=tmp_path)
    assert op.n_vertices == cloud.n_vertices and op.nnz > 0
    assert [path.stem for path in tmp_path.glob("*.zop")] == [cache_key(mesh_from_cloud(cloud), config, "front")]


def test_operator_of_another_backend_version_is_rebuilt(tmp_path, monkeypatch):
    surface = bumpy_sphere()
    config = PatchConfig(r0=2.0, n_samples=800)
    build_patch_operator(surface, config, cache_dir=tmp_path)
    old_key = cache_key(surface, config)
    monkeypatch.setitem(BACKEND_VERSIONS, "front", BACKEND_VERSIONS["front"] + 1)
    new_key = cache_key(surface, config)
    assert new_key != old_key
    build_patch_operator(surface, config, cache_dir=tmp_path)
    assert sorted(path.stem for path in tmp_path.glob("*.zop")) == sorted([old_key, new_key])
