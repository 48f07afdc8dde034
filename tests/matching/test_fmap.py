"""The Laplace-Beltrami eigenbasis and the functional-map layer: orthonormality and the cache, the identity
map of a shape onto itself, a rotated and re-indexed copy recovered vertex by vertex, ZoomOut, and the
layer's gradients (float64 gradcheck), and heat smoothing against the sphere's degree-one harmonics."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from meshes import icosphere

from zernet.geometry import Surface
from zernet.matching.fmap import (
    cycle_confidence,
    fmap_from_pointmap,
    functional_map,
    pointmap_from_fmap,
    resolvent_mask,
    zoomout,
)
from zernet.operators.spectral import heat_kernel_signature, heat_smoothed, laplacian, laplacian_eigenbasis


def bumpy_ellipsoid() -> Surface:
    """642 vertices, distinct axes and radial noise: no symmetry, so no two vertices look alike spectrally."""
    sphere = icosphere(3, noise=0.03, seed=1)
    return Surface(sphere.vertices * np.array([1.0, 1.4, 1.9]), sphere.faces, name="ellipsoid")


def random_rotation(seed: int) -> np.ndarray:
    q, r = np.linalg.qr(np.random.default_rng(seed).standard_normal((3, 3)))
    q *= np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def tensors(basis, k):
    b = basis.truncated(k)
    return (torch.as_tensor(b.eigenvectors), torch.as_tensor(b.mass), torch.as_tensor(b.eigenvalues))


def test_eigenbasis_is_mass_orthonormal_sorted_and_cached(tmp_path):
    surface = bumpy_ellipsoid()
    basis = laplacian_eigenbasis(surface, 20, cache_dir=tmp_path)
    gram = basis.eigenvectors.T @ (basis.mass[:, None] * basis.eigenvectors)
    np.testing.assert_allclose(gram, np.eye(20), atol=1e-8)
    assert basis.eigenvalues[0] == pytest.approx(0.0, abs=1e-8)
    assert np.all(np.diff(basis.eigenvalues) >= 0)
    np.testing.assert_allclose(basis.mass.sum(), surface.area, rtol=1e-9)
    files = list((tmp_path / "spectral").glob("*.npz"))
    assert len(files) == 1
    again = laplacian_eigenbasis(surface, 20, cache_dir=tmp_path)
    np.testing.assert_array_equal(again.eigenvectors, basis.eigenvectors)


def test_sphere_spectrum_and_point_cloud_basis():
    """Unit sphere: λ = l (l + 1) with multiplicity 2 l + 1; the cloud Laplacian of its vertices agrees."""
    sphere = icosphere(3)
    for surface in (sphere, Surface(sphere.vertices, None, name="cloud")):
        values = laplacian_eigenbasis(surface, 9).eigenvalues
        np.testing.assert_allclose(values[1:4], 2.0, rtol=0.03)
        np.testing.assert_allclose(values[4:9], 6.0, rtol=0.05)


def test_identity_map_on_the_same_shape():
    surface = bumpy_ellipsoid()
    basis = laplacian_eigenbasis(surface, 30)
    vectors, mass, values = tensors(basis, 30)
    descriptors = torch.as_tensor(np.random.default_rng(0).standard_normal((surface.n_vertices, 40)))
    fmap = functional_map(descriptors, descriptors, vectors, vectors, mass, mass, values, values)
    np.testing.assert_allclose(fmap.numpy(), np.eye(30), atol=1e-6)
    np.testing.assert_array_equal(pointmap_from_fmap(fmap.numpy(), basis, basis), np.arange(surface.n_vertices))
    assert (
        cycle_confidence(np.arange(surface.n_vertices), np.arange(surface.n_vertices), surface.vertices, 0.1).min()
        == 1.0
    )


def test_rotated_and_reindexed_copy_is_recovered_vertex_by_vertex():
    """Y = X rotated and its vertices permuted: the layer on descriptors that follow the vertices finds the
    isometry's map (diagonal ±1), its point map is the permutation, and ZoomOut keeps it."""
    x = bumpy_ellipsoid()
    n = x.n_vertices
    permutation = np.random.default_rng(3).permutation(n)  # Y vertex i is X vertex permutation[i]
    inverse = np.argsort(permutation)
    y = Surface(x.vertices[permutation] @ random_rotation(4).T + 5.0, inverse[x.faces], name="copy")
    basis_x, basis_y = laplacian_eigenbasis(x, 40), laplacian_eigenbasis(y, 40)
    descriptors_x = np.random.default_rng(5).standard_normal((n, 40))
    k = 25
    fmap_xy = functional_map(
        torch.as_tensor(descriptors_x), torch.as_tensor(descriptors_x[permutation]), *_pairwise(basis_x, basis_y, k)
    ).numpy()
    np.testing.assert_allclose(np.abs(fmap_xy), np.eye(k), atol=1e-5)
    pointmap_yx = pointmap_from_fmap(fmap_xy, basis_x, basis_y)
    np.testing.assert_array_equal(pointmap_yx, permutation)
    refined, refined_fmap = zoomout(pointmap_yx, basis_x, basis_y, k, 40, step=5)
    np.testing.assert_array_equal(refined, permutation)
    assert refined_fmap.shape == (40, 40)
    np.testing.assert_allclose(fmap_from_pointmap(permutation, basis_x, basis_y, k, k), fmap_xy, atol=1e-5)


def _pairwise(basis_x, basis_y, k):
    vx, mx, lx = tensors(basis_x, k)
    vy, my, ly = tensors(basis_y, k)
    return vx, vy, mx, my, lx, ly


def test_zoomout_repairs_a_noisy_initial_map():
    """A map right at low frequency, with 30 % of the vertices sent to a random neighbour's place, comes back
    to within one ring of exact after ZoomOut."""
    x = bumpy_ellipsoid()
    basis = laplacian_eigenbasis(x, 60)
    rng = np.random.default_rng(0)
    noisy = np.arange(x.n_vertices)
    wrong = rng.random(x.n_vertices) < 0.3
    edges = x.edges()
    neighbour = {int(a): int(b) for a, b in edges}
    noisy[wrong] = [neighbour.get(int(i), int(i)) for i in np.flatnonzero(wrong)]
    refined, _ = zoomout(noisy, basis, basis, 10, 60, step=5)
    assert np.mean(refined == np.arange(x.n_vertices)) > 0.95


def test_layer_gradients_float64():
    rng = np.random.default_rng(0)
    n_x, n_y, k_x, k_y, d = 12, 10, 5, 4, 7

    def leaf(*shape, positive=False):
        values = rng.random(shape) + 0.5 if positive else rng.standard_normal(shape)
        return torch.tensor(values, dtype=torch.float64, requires_grad=True)

    inputs = (
        leaf(n_x, d),
        leaf(n_y, d),
        leaf(n_x, k_x),
        leaf(n_y, k_y),
        leaf(n_x, positive=True),
        leaf(n_y, positive=True),
        leaf(k_x, positive=True),
        leaf(k_y, positive=True),
    )
    assert torch.autograd.gradcheck(lambda *a: functional_map(*a, regularisation=0.1), inputs)


def test_resolvent_mask_is_zero_on_equal_frequencies():
    values = torch.tensor([0.0, 1.0, 4.0, 9.0])
    mask = resolvent_mask(values, values)
    assert torch.allclose(torch.diagonal(mask), torch.zeros(4))
    assert (mask + torch.eye(4) > 0).all()


def test_heat_kernel_signature_is_scale_free():
    surface = bumpy_ellipsoid()
    small = heat_kernel_signature(laplacian_eigenbasis(surface, 30))
    large = heat_kernel_signature(laplacian_eigenbasis(Surface(3 * surface.vertices, surface.faces), 30))
    np.testing.assert_allclose(small, large, rtol=1e-4, atol=1e-5)


def test_heat_kernel_signature_of_a_surface_in_pieces_stays_bounded():
    # A one-sided scan comes in pieces; each piece's constant eigenfunction is 1 / its area and never
    # decays, which made a small fragment's signature 1e4 times the mean. The zero eigenvalues count as one
    # constant: on a connected surface the textbook sum, on pieces of the same order as on the whole.
    whole = bumpy_ellipsoid()
    basis = laplacian_eigenbasis(whole, 30)
    times = np.geomspace(4 * np.log(10) / basis.eigenvalues[-1], 4 * np.log(10) / basis.eigenvalues[1], 16)
    textbook = basis.eigenvectors**2 @ np.exp(-np.outer(basis.eigenvalues, times))
    textbook /= basis.mass @ textbook / basis.mass.sum()
    np.testing.assert_allclose(heat_kernel_signature(basis), textbook, rtol=1e-4)
    fragment = Surface(0.05 * whole.vertices + 10.0, whole.faces)
    pieces = Surface(np.vstack([whole.vertices, fragment.vertices]), np.vstack([whole.faces, fragment.faces + 642]))
    signature = heat_kernel_signature(laplacian_eigenbasis(pieces, 30))
    assert np.isfinite(signature).all() and signature.max() < 20


def test_zoomout_maps_a_part_into_its_whole():
    # Y is 60 % of X (a cap cut off), as a one-sided scan is a part of a body: ZoomOut repairs a map of the
    # part with 30 % of its vertices sent anywhere on the whole.
    x = bumpy_ellipsoid()
    kept = np.flatnonzero(x.vertices[:, 2] < np.quantile(x.vertices[:, 2], 0.6))
    inside = np.isin(x.faces, kept).all(axis=1)
    renumber = np.full(x.n_vertices, -1)
    renumber[kept] = np.arange(len(kept))
    y = Surface(x.vertices[kept], renumber[x.faces[inside]], name="part")
    basis_x, basis_y = laplacian_eigenbasis(x, 60), laplacian_eigenbasis(y, 60)
    rng = np.random.default_rng(0)
    noisy = kept.copy()
    wrong = rng.random(len(kept)) < 0.3
    noisy[wrong] = rng.choice(x.n_vertices, wrong.sum())
    refined, _ = zoomout(noisy, basis_x, basis_y, 10, 60, step=5)

    def mean_error(pointmap):
        return np.linalg.norm(x.vertices[pointmap] - x.vertices[kept], axis=1).mean()

    assert mean_error(refined) < 0.1 * mean_error(noisy)


@pytest.mark.parametrize("as_cloud", [False, True])
def test_smoothing_damps_a_degree_one_harmonic_by_one_over_one_plus_two_t(as_cloud):
    sphere = icosphere(4)
    surface = Surface(sphere.vertices) if as_cloud else sphere
    # On the unit sphere x, y, z are eigenfunctions of the Laplacian with eigenvalue 2: one implicit heat step
    # of length t divides them by 1 + 2t; a constant stays as it is and the mass-weighted mean is kept.
    time = 0.05
    values = np.column_stack([surface.vertices, np.ones(surface.n_vertices)])
    smoothed = heat_smoothed(surface, values, time)
    np.testing.assert_allclose(smoothed[:, 3], 1.0, atol=1e-10)
    np.testing.assert_allclose(smoothed[:, :3], surface.vertices / (1 + 2 * time), atol=0.01)
    _, mass = laplacian(surface)
    np.testing.assert_allclose(mass @ smoothed, mass @ values, atol=1e-10)
    assert heat_smoothed(surface, values, 0.0) is values
