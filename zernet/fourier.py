r"""Real functions on the circle, stored by their Fourier coefficients.

A circle function ``h(ψ)`` of order ``L`` is kept as its real Fourier coefficients in the layout
``[a_0, a_1, b_1, ..., a_L, b_L]`` along a *direction axis* of length ``2L + 1``:

.. math::
    h(ψ) = a_0 + \sum_{\ell=1}^{L} a_\ell \cos \ell ψ + b_\ell \sin \ell ψ .

This is the harmonic layout of :mod:`zernet.nn.pooling` (there along the first axis).
:func:`fourier_to_samples` / :func:`samples_to_fourier` convert to and from ``s`` samples at
``ψ_a = 2π a / s``; :func:`rotate_fourier` gives the coefficients of ``h(ψ + δ)`` (the same convention as
:func:`zernet.zernike.rotate_coefficients`: each ``(a_ℓ, b_ℓ)`` turns by ``[[cos ℓδ, sin ℓδ], [-sin ℓδ,
cos ℓδ]]``). :func:`harmonic_basis` is the change to complex exponentials ``e^{iℓψ}``, in which every
rotation is diagonal. The directional operators (:mod:`zernet.operators.directional`) and layers
(:mod:`zernet.nn.directional`) use these helpers.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

__all__ = [
    "fourier_dim",
    "fourier_orders",
    "fourier_order_of",
    "trig_table",
    "sample_angles",
    "fourier_to_samples",
    "samples_to_fourier",
    "fourier_rotation_matrix",
    "rotate_fourier",
    "harmonic_basis",
]


def fourier_dim(order: int) -> int:
    """Length ``2 L + 1`` of the direction axis for Fourier order ``L``."""
    if order < 0:
        raise ValueError(f"Fourier order must be >= 0, got {order}")
    return 2 * int(order) + 1


def fourier_orders(order: int) -> np.ndarray:
    """Order ``ℓ`` of every entry of the layout ``[a_0, a_1, b_1, ...]``, shape ``(2L + 1,)``."""
    return np.concatenate([[0], np.repeat(np.arange(1, order + 1), 2)]).astype(np.int64)


def trig_table(angles: np.ndarray, order: int) -> np.ndarray:
    """``T[a, r] = T_r(ψ_a)`` for ``T = (1, cos ψ, sin ψ, ..., cos Lψ, sin Lψ)``, shape ``(len, 2L + 1)``."""
    angles = np.asarray(angles, dtype=np.float64)
    table = np.empty((angles.shape[0], fourier_dim(order)), dtype=np.float64)
    table[:, 0] = 1.0
    for ell in range(1, order + 1):
        table[:, 2 * ell - 1] = np.cos(ell * angles)
        table[:, 2 * ell] = np.sin(ell * angles)
    return table


def sample_angles(s: int) -> np.ndarray:
    """The ``s`` equally spaced angles ``ψ_a = 2π a / s`` (float64)."""
    if s < 1:
        raise ValueError(f"angular resolution s must be >= 1, got {s}")
    return np.arange(s, dtype=np.float64) * (2.0 * math.pi / s)


def fourier_order_of(length: int) -> int:
    """Order ``L`` of a direction axis of length ``2L + 1`` (an error for even lengths)."""
    if length < 1 or length % 2 == 0:
        raise ValueError(f"a direction axis in Fourier layout has odd length 2L+1, got {length}")
    return (length - 1) // 2


def fourier_to_samples(coeffs: Tensor, s: int, dim: int = -2) -> Tensor:
    """Values ``h(ψ_a)`` at ``ψ_a = 2π a / s`` of circle functions given by Fourier coefficients.

    Args:
        coeffs: real Fourier coefficients, direction axis (length ``2L + 1``) at ``dim``,
            e.g. ``(N, 2L + 1, C)``.
        s: number of equally spaced angles.
        dim: direction axis.

    Returns:
        Same shape with the direction axis replaced by ``s`` samples, e.g. ``(N, s, C)``.
    """
    order = fourier_order_of(coeffs.shape[dim])
    table = torch.as_tensor(trig_table(sample_angles(s), order), dtype=coeffs.dtype, device=coeffs.device)
    x = coeffs.movedim(dim, -1)
    return (x @ table.T).movedim(-1, dim)


def samples_to_fourier(samples: Tensor, order: int, dim: int = -2) -> Tensor:
    """Fourier coefficients up to order ``L`` of ``s`` equally spaced samples (the discrete Fourier transform).

    Exact inverse of :func:`fourier_to_samples` for functions of order ``<= L``; requires ``2L < s``.
    It commutes with cyclic shifts of the samples: shifting by ``a`` samples equals
    ``rotate_fourier(·, 2π a / s)``.

    Args:
        samples: values at ``ψ_a = 2π a / s`` along ``dim``, e.g. ``(N, s, C)``.
        order: ``L``.
        dim: direction axis.

    Returns:
        Same shape with ``s`` replaced by ``2L + 1``, e.g. ``(N, 2L + 1, C)``.
    """
    s = samples.shape[dim]
    if 2 * order >= s:
        raise ValueError(f"{s} samples determine Fourier orders < s/2 only; got order {order}")
    table = trig_table(sample_angles(s), order)  # (s, 2L+1)
    weights = np.full(fourier_dim(order), 2.0 / s)
    weights[0] = 1.0 / s
    dft = torch.as_tensor(table * weights, dtype=samples.dtype, device=samples.device)  # (s, 2L+1)
    x = samples.movedim(dim, -1)
    return (x @ dft).movedim(-1, dim)


def fourier_rotation_matrix(delta, order: int):
    """Matrix ``Q(δ)`` with ``rotate_fourier(c, δ) = Q(δ) @ c``; numpy (float64) or torch like ``delta``.

    Args:
        delta: angle(s), scalar or shape ``B``.
        order: ``L``.

    Returns:
        Shape ``B + (2L + 1, 2L + 1)``.
    """
    is_torch = isinstance(delta, torch.Tensor)
    lib = torch if is_torch else np
    if not is_torch:
        delta = np.asarray(delta, dtype=np.float64)
    d = fourier_dim(order)
    out = (
        torch.zeros(delta.shape + (d, d), dtype=delta.dtype, device=delta.device)
        if is_torch
        else np.zeros(delta.shape + (d, d))
    )
    out[..., 0, 0] = 1.0
    for ell in range(1, order + 1):
        c, s = lib.cos(ell * delta), lib.sin(ell * delta)
        i, k = 2 * ell - 1, 2 * ell
        out[..., i, i] = c
        out[..., i, k] = s
        out[..., k, i] = -s
        out[..., k, k] = c
    return out


def rotate_fourier(coeffs: Tensor, delta, dim: int = -2) -> Tensor:
    """Coefficients of ``h(ψ + δ)`` given those of ``h(ψ)``.

    Args:
        coeffs: Fourier coefficients with the direction axis (``2L + 1``) at ``dim``, e.g. ``(N, 2L + 1, C)``.
        delta: scalar angle, or a tensor broadcastable against ``coeffs`` with the direction axis removed
            (e.g. one angle per vertex, shape ``(N, 1)`` for ``(N, 2L + 1, C)``).
        dim: direction axis.

    Returns:
        Rotated coefficients, same shape.
    """
    order = fourier_order_of(coeffs.shape[dim])
    x = coeffs.movedim(dim, -1)
    delta = torch.as_tensor(delta, dtype=x.dtype, device=x.device)
    q = fourier_rotation_matrix(delta, order)  # delta.shape + (d, d)
    return (q @ x.unsqueeze(-1)).squeeze(-1).movedim(-1, dim)


def harmonic_basis(order: int) -> np.ndarray:
    r"""Change of basis ``U`` from the real layout to complex exponentials: ``ĥ = U c``, complex128.

    Row ``ℓ + L`` (``ℓ = -L..L``) gives ``ĥ_ℓ`` with ``h(ψ) = Σ_ℓ ĥ_ℓ e^{iℓψ}``: ``ĥ_0 = a_0``,
    ``ĥ_{±ℓ} = (a_ℓ ∓ i b_ℓ) / 2``. In this basis a rotation is diagonal,
    ``U Q(δ) U^{-1} = diag(e^{iℓδ})`` (:func:`fourier_rotation_matrix`), which is why a product of
    harmonics of orders ``ℓ`` and ``m`` only reaches orders ``ℓ + m`` and ``ℓ - m``. ``U U^H = diag(w)``
    with ``w_0 = 1`` and ``w_ℓ = 1/2`` otherwise, so ``U^{-1} = U^H diag(w)^{-1}``.

    Args:
        order: ``L``.

    Returns:
        ``(2L + 1, 2L + 1)`` complex matrix, rows ``ℓ = -L..L``, columns the real layout.
    """
    d = fourier_dim(order)
    u = np.zeros((d, d), dtype=np.complex128)
    u[order, 0] = 1.0
    for ell in range(1, order + 1):
        a, b = 2 * ell - 1, 2 * ell
        u[order + ell, a], u[order + ell, b] = 0.5, -0.5j
        u[order - ell, a], u[order - ell, b] = 0.5, 0.5j
    return u
