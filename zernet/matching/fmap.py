r"""Functional maps: the differentiable layer and the confidence; point maps from functional maps and back and
ZoomOut are re-exported from :mod:`zernet.operators.spectral`, where they live (the correspondence refinement
of :mod:`zernet.training` uses them too, and training sits below matching).

Convention (as in pyFM and DiffusionNet): a functional map ``C_xy`` (k_y, k_x) carries a function on a
surface X, given by its spectral coefficients on X, to a function on Y. A point map ``T: Y -> X`` (one X
vertex per Y vertex, an array ``(N_y,)``) induces ``C_xy = Φ_yᵀ M_y Φ_x[T]`` (the pull-back: ``f ∘ T``), and
conversely ``C_xy`` gives ``T(y) = argmin_x ‖Φ_x[x] - Φ_y[y] C_xy‖`` (nearest neighbours in the spectral
embedding). So the vertex map *source -> target* goes with ``C_target,source`` (k_s, k_t), the map that
carries functions on the target to the source.

The layer (:func:`functional_map`) is the regularised least squares of GeomFmaps (Donati et al. 2020), with
the resolvent Laplacian-commutativity mask of Ren et al. 2019 as in DiffusionNet's functional-map example:
descriptors ``F_x`` (N_x, d) and ``F_y`` (N_y, d) are projected, ``A = Φ_xᵀ M_x F_x`` (k_x, d),
``B = Φ_yᵀ M_y F_y`` (k_y, d), and

.. math:: C = \arg\min_C \|C A - B\|^2 + \lambda \sum_{ij} \mathrm{mask}_{ij} C_{ij}^2,

whose rows separate: ``c_i = (A Aᵀ + λ diag(mask_i))⁻¹ A B_iᵀ``, one k_x × k_x solve per row, batched.
"""

from __future__ import annotations

import numpy as np
import torch

from zernet.operators.spectral import fmap_from_pointmap, nearest_rows, pointmap_from_fmap, zoomout

__all__ = [
    "resolvent_mask",
    "functional_map",
    "fmap_from_pointmap",
    "nearest_rows",
    "pointmap_from_fmap",
    "zoomout",
    "cycle_confidence",
]


def resolvent_mask(eigenvalues_x: torch.Tensor, eigenvalues_y: torch.Tensor, gamma: float = 0.5) -> torch.Tensor:
    """(k_y, k_x) the resolvent commutativity penalty of each entry of ``C_xy`` (Ren et al. 2019).

    Eigenvalues are divided by the largest of both sets and raised to ``gamma``; each ``μ`` becomes the
    point ``(μ / (μ² + 1), 1 / (μ² + 1))`` and the mask is the squared distance between the points of
    ``μ_y[i]`` and ``μ_x[j]``: zero where the two frequencies agree, so an isometry's (near-diagonal) map
    is not penalised, and bounded for high frequencies, unlike ``(λ_i - λ_j)²``.
    """
    scale = torch.maximum(eigenvalues_x.max(), eigenvalues_y.max()).clamp_min(1e-12)
    mu_x = (eigenvalues_x / scale).clamp_min(0) ** gamma
    mu_y = (eigenvalues_y / scale).clamp_min(0) ** gamma
    real_x, imag_x = mu_x / (mu_x**2 + 1), 1 / (mu_x**2 + 1)
    real_y, imag_y = mu_y / (mu_y**2 + 1), 1 / (mu_y**2 + 1)
    return (real_y[:, None] - real_x[None, :]) ** 2 + (imag_y[:, None] - imag_x[None, :]) ** 2


def functional_map(
    descriptors_x: torch.Tensor,
    descriptors_y: torch.Tensor,
    eigenvectors_x: torch.Tensor,
    eigenvectors_y: torch.Tensor,
    mass_x: torch.Tensor,
    mass_y: torch.Tensor,
    eigenvalues_x: torch.Tensor,
    eigenvalues_y: torch.Tensor,
    regularisation: float = 1e-3,
    gamma: float = 0.5,
) -> torch.Tensor:
    """The functional map ``C_xy`` (k_y, k_x) that best carries the descriptors of X to those of Y, with the
    commutativity penalty (module docstring). Differentiable in everything (one batched linear solve).

    Args:
        descriptors_x: (N_x, d); descriptors_y: (N_y, d) per-vertex descriptors.
        eigenvectors_x: (N_x, k_x); eigenvectors_y: (N_y, k_y) M-orthonormal eigenvectors.
        mass_x: (N_x,); mass_y: (N_y,) lumped masses.
        eigenvalues_x: (k_x,); eigenvalues_y: (k_y,).
        regularisation: λ, the weight of the commutativity penalty.
        gamma: the resolvent's exponent (:func:`resolvent_mask`).
    """
    coefficients_x = eigenvectors_x.T @ (mass_x[:, None] * descriptors_x)  # A: (k_x, d)
    coefficients_y = eigenvectors_y.T @ (mass_y[:, None] * descriptors_y)  # B: (k_y, d)
    mask = resolvent_mask(eigenvalues_x, eigenvalues_y, gamma)  # (k_y, k_x)
    gram = coefficients_x @ coefficients_x.T  # A Aᵀ: (k_x, k_x)
    lhs = gram.unsqueeze(0) + regularisation * torch.diag_embed(mask)  # (k_y, k_x, k_x)
    rhs = coefficients_y @ coefficients_x.T  # rows B_i Aᵀ: (k_y, k_x)
    return torch.linalg.solve(lhs, rhs.unsqueeze(-1)).squeeze(-1)


def cycle_confidence(
    pointmap_xy: np.ndarray, pointmap_yx: np.ndarray, vertices_x: np.ndarray, scale: float
) -> np.ndarray:
    """(N_x,) confidence in [0, 1] of each X vertex's match: how close the round trip X -> Y -> X comes back.

    ``exp(-(d / scale)²)`` with ``d`` the Euclidean distance on X between a vertex and the image of its
    image (Euclidean within one surface: no pose enters). Where the two directions agree the map is
    locally bijective; a flipped limb or a part missing on Y sends the round trip elsewhere. ``scale``:
    a length on X (the matcher uses 5 % of the square root of X's area).
    """
    round_trip = np.asarray(pointmap_yx)[np.asarray(pointmap_xy)]
    distance = np.linalg.norm(vertices_x[round_trip] - vertices_x, axis=1)
    return np.exp(-((distance / scale) ** 2))
