"""The complex harmonic basis of zernet/fourier.py: the identities the directional plan relies on."""

import numpy as np
import pytest
import torch

from zernet.fourier import fourier_rotation_matrix, harmonic_basis, samples_to_fourier, trig_table


@pytest.mark.parametrize("order", [0, 1, 3])
def test_harmonic_basis_expands_in_exponentials(order):
    """trig_table(ψ) c = Σ_ℓ (U c)_ℓ e^{iℓψ} for any coefficients and angles."""
    rng = np.random.default_rng(order)
    c = rng.normal(size=2 * order + 1)
    psi = rng.uniform(-np.pi, np.pi, 9)
    u = harmonic_basis(order)
    exponentials = np.exp(1j * np.outer(psi, np.arange(-order, order + 1)))
    np.testing.assert_allclose(exponentials @ (u @ c), trig_table(psi, order) @ c, atol=1e-13)
    # real functions: ĥ_{-ℓ} is the conjugate of ĥ_ℓ
    h = u @ c
    np.testing.assert_allclose(h[::-1], h.conj(), atol=1e-15)


def test_rotations_are_diagonal_and_the_basis_is_orthogonal():
    order = 4
    u = harmonic_basis(order)
    for delta in (0.3, -2.1):
        diagonal = u @ fourier_rotation_matrix(delta, order) @ np.linalg.inv(u)
        np.testing.assert_allclose(diagonal, np.diag(np.exp(1j * delta * np.arange(-order, order + 1))), atol=1e-13)
    w = np.full(2 * order + 1, 0.5)
    w[order] = 1.0
    np.testing.assert_allclose(u @ u.conj().T, np.diag(w), atol=1e-15)
    np.testing.assert_allclose(np.linalg.inv(u), u.conj().T @ np.diag(1 / w), atol=1e-13)


def test_a_product_of_two_harmonics_only_reaches_the_sum_and_difference_orders():
    """cos/sin of order 3 times cos/sin of order 1: orders 2 and 4 only (what the plan prunes by)."""
    s = 32
    psi = 2 * np.pi * np.arange(s) / s
    rng = np.random.default_rng(0)
    f = rng.normal() * np.cos(3 * psi) + rng.normal() * np.sin(3 * psi)
    g = rng.normal() * np.cos(psi) + rng.normal() * np.sin(psi)
    coeffs = samples_to_fourier(torch.as_tensor(f * g)[:, None], 6, dim=0)[:, 0].numpy()
    spectrum = np.abs(harmonic_basis(6) @ coeffs)[6:]  # |ĥ_ℓ|, ℓ = 0..6
    assert np.all(spectrum[[2, 4]] > 1e-3)
    np.testing.assert_allclose(spectrum[[0, 1, 3, 5, 6]], 0, atol=1e-13)
