"""Tests for zernet.zernike: orthonormality, rotation convention, index helpers, numpy/torch agreement."""

import math

import numpy as np
import pytest
import torch

from zernet.zernike import (
    harmonic_pairs,
    index_to_nm,
    n_max_for,
    nm_to_index,
    num_bases,
    orders,
    rotate_coefficients,
    rotation_matrix,
    zernike_basis,
)


def disk_quadrature(n_r=24, n_t=64):
    """Nodes and weights integrating polynomials of degree < 2 n_r in r (weight r) and trig degree < n_t."""
    x, w = np.polynomial.legendre.leggauss(n_r)
    r = 0.5 * (x + 1.0)
    wr = 0.5 * w * r  # dA = r dr dθ
    theta = 2 * np.pi * np.arange(n_t) / n_t  # trapezoid rule: exact for periodic trig polynomials
    wt = np.full(n_t, 2 * np.pi / n_t)
    R, T = np.meshgrid(r, theta, indexing="ij")
    W = np.outer(wr, wt)
    return R.ravel(), T.ravel(), W.ravel()


def project(func, n_max, quad=None):
    """Zernike coefficients of ``func(r, θ)`` by quadrature (orthonormal basis)."""
    r, t, w = quad or disk_quadrature()
    Z = zernike_basis(r, t, n_max)
    return Z.T @ (w * func(r, t))


@pytest.mark.parametrize("n_max", range(9))
def test_gram_matrix_is_identity(n_max):
    r, t, w = disk_quadrature()
    Z = zernike_basis(r, t, n_max)
    gram = Z.T @ (w[:, None] * Z)
    np.testing.assert_allclose(gram, np.eye(num_bases(n_max)), atol=1e-10)


def test_rotated_coefficients_reproduce_rotated_function():
    rng = np.random.default_rng(0)
    n_max = 6
    a = rng.standard_normal(num_bases(n_max))
    r = rng.uniform(0, 1, 200)
    t = rng.uniform(-np.pi, np.pi, 200)
    for phi in (0.3, -1.2, 2.0 * np.pi / 3, 5.0):
        direct = zernike_basis(r, t + phi, n_max) @ a
        rotated = zernike_basis(r, t, n_max) @ rotate_coefficients(a, phi)
        np.testing.assert_allclose(rotated, direct, atol=1e-12)


def test_rotation_composes_and_inverts():
    rng = np.random.default_rng(1)
    a = rng.standard_normal((num_bases(5), 3))
    for alpha, beta in [(0.4, 1.1), (-2.0, 0.7), (3.0, 3.5)]:
        two_steps = rotate_coefficients(rotate_coefficients(a, alpha, dim=0), beta, dim=0)
        np.testing.assert_allclose(two_steps, rotate_coefficients(a, alpha + beta, dim=0), atol=1e-12)
        Ra, Rb, Rab = (rotation_matrix(p, 5) for p in (alpha, beta, alpha + beta))
        np.testing.assert_allclose(Ra @ Rb, Rab, atol=1e-12)
        np.testing.assert_allclose(Ra.T @ Ra, np.eye(num_bases(5)), atol=1e-12)
    np.testing.assert_allclose(rotate_coefficients(a, 2 * np.pi, dim=0), a, atol=1e-12)


def test_rotation_matrix_matches_rotate_coefficients():
    rng = np.random.default_rng(2)
    a = rng.standard_normal(num_bases(4))
    for phi in (0.0, 0.9, -2.5):
        np.testing.assert_allclose(rotation_matrix(phi, 4) @ a, rotate_coefficients(a, phi), atol=1e-13)


def test_batched_angles():
    rng = np.random.default_rng(3)
    N, k, d = 7, num_bases(5), 4
    F = rng.standard_normal((N, k, d))
    phi = rng.uniform(-np.pi, np.pi, N)
    batched = rotate_coefficients(F, phi[:, None], dim=1)
    for p in range(N):
        np.testing.assert_allclose(batched[p], rotate_coefficients(F[p], phi[p], dim=0), atol=1e-13)
    mats = rotation_matrix(phi, 5)
    assert mats.shape == (N, k, k)
    np.testing.assert_allclose(np.einsum("nij,njd->nid", mats, F), batched, atol=1e-13)
    Ft = torch.as_tensor(F)
    bt = rotate_coefficients(Ft, torch.as_tensor(phi)[:, None], dim=1)
    np.testing.assert_allclose(bt.numpy(), batched, atol=1e-13)


def test_band_limited_product_integral_is_dot_product():
    rng = np.random.default_rng(4)
    n_max = 5
    a, b = rng.standard_normal((2, num_bases(n_max)))
    r, t, w = disk_quadrature()
    Z = zernike_basis(r, t, n_max)
    integral = np.sum(w * (Z @ a) * (Z @ b))
    assert integral == pytest.approx(a @ b, abs=1e-10)


def test_projection_of_analytic_function_roundtrips():
    # A polynomial of degree <= n_max in x, y lies in the span: projection then evaluation is exact.
    n_max = 4
    f = lambda r, t: (r * np.cos(t)) ** 3 - 2 * (r * np.sin(t)) * (r * np.cos(t)) + 0.5  # noqa: E731
    a = project(f, n_max)
    r = np.linspace(0, 1, 11)
    t = np.linspace(-3, 3, 11)
    np.testing.assert_allclose(zernike_basis(r, t, n_max) @ a, f(r, t), atol=1e-10)


def test_index_helpers_round_trip():
    for j in range(num_bases(12)):
        n, m = index_to_nm(j)
        assert abs(m) <= n and (n - m) % 2 == 0
        assert nm_to_index(n, m) == j
    assert index_to_nm(0) == (0, 0)
    assert index_to_nm(4) == (2, 0)
    assert list(orders(2)) == [0, -1, 1, -2, 0, 2]
    for n_max in range(10):
        assert n_max_for(num_bases(n_max)) == n_max
    with pytest.raises(ValueError):
        nm_to_index(2, 1)
    with pytest.raises(ValueError):
        index_to_nm(-1)


@pytest.mark.parametrize("k", [0, 2, 4, 5, 20, 22])
def test_n_max_for_rejects_non_triangular(k):
    with pytest.raises(ValueError, match="not a complete set"):
        n_max_for(k)


def test_harmonic_pairs_partition_the_bases():
    for n_max in range(8):
        zero, ci, si, mo = harmonic_pairs(n_max)
        allidx = np.sort(np.concatenate([zero, ci, si]))
        np.testing.assert_array_equal(allidx, np.arange(num_bases(n_max)))
        m = orders(n_max)
        np.testing.assert_array_equal(m[zero], 0)
        np.testing.assert_array_equal(m[ci], mo)
        np.testing.assert_array_equal(m[si], -mo)


def test_numpy_and_torch_agree():
    rng = np.random.default_rng(5)
    r = rng.uniform(0, 1, (3, 5))
    t = rng.uniform(-np.pi, np.pi, (3, 5))
    zn = zernike_basis(r, t, 6)
    zt = zernike_basis(torch.as_tensor(r), torch.as_tensor(t), 6)
    assert isinstance(zt, torch.Tensor) and zt.dtype == torch.float64 and zt.shape == (3, 5, 28)
    np.testing.assert_allclose(zt.numpy(), zn, atol=1e-12)
    z32 = zernike_basis(torch.as_tensor(r, dtype=torch.float32), torch.as_tensor(t, dtype=torch.float32), 6)
    assert z32.dtype == torch.float32
    np.testing.assert_allclose(z32.numpy(), zn, atol=1e-4)
    a = rng.standard_normal((4, 28))
    phi = 0.77
    np.testing.assert_allclose(
        rotate_coefficients(torch.as_tensor(a), phi).numpy(), rotate_coefficients(a, phi), atol=1e-13
    )
    np.testing.assert_allclose(
        rotation_matrix(torch.tensor(phi, dtype=torch.float64), 6).numpy(), rotation_matrix(phi, 6), atol=1e-13
    )


def test_basis_values_known():
    # Z_0^0 = 1/sqrt(pi); Z_1^1 = 2 r cos θ / sqrt(pi); Z_2^0 = sqrt(3/pi) (2 r^2 - 1)
    z = zernike_basis(np.array(0.5), np.array(0.3), 2)
    assert z[0] == pytest.approx(1 / math.sqrt(math.pi))
    assert z[2] == pytest.approx(2 * 0.5 * math.cos(0.3) / math.sqrt(math.pi))
    assert z[1] == pytest.approx(2 * 0.5 * math.sin(0.3) / math.sqrt(math.pi))
    assert z[4] == pytest.approx(math.sqrt(3 / math.pi) * (2 * 0.25 - 1))
