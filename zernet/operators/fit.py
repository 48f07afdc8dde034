"""The least-squares fit of Zernike coefficients to the samples of each patch: a ridge that spares the piston.

For vertex ``p`` with ``n_p`` patch samples at normalised polar coordinates ``(r_j, θ_j)`` and Zernike
values ``B_p`` (``n_p × k``), the fit matrix is

    ``P_p = (B_pᵀ B_p + λ W)⁻¹ B_pᵀ``,   ``W = diag(0, 1, 1, ..., 1)``:

the paper's ridge ``λ I`` on every basis but the piston.

Why the piston is spared: ``λ I`` shrinks every coefficient, the piston included, so a constant field comes
out low by about ``λ / eigenvalue``, a bias that grows where a patch covers less of the disk. With
``W_00 = 0`` a constant field is fitted exactly on every non-empty patch (``W a = 0`` for a pure piston, so
``P_p B_p a = a``): its piston is exact and every other coefficient 0, whatever the coverage.
``B_pᵀB_p + λW`` is still positive definite for any non-empty patch (the piston column of ``B_p`` is a
non-zero constant), so truncated boundary patches stay well-posed: the modes the samples cannot see
(eigenvalues ≪ λ) shrink to 0 instead of exploding, the least-squares counterpart of the paper's zero
padding. A vertex with no sample gets all-zero rows.

Why every other basis gets the same weight: a penalty that grows with the degree (``n (n + 2)``, a
smoothness prior; tried) leaves the low-degree combinations that a patch's samples barely separate (an
annulus ``r0/4 <= r <= r0`` hardly tells the piston from ``Z_2^0``) almost undamped. Their coefficients then
carry sampling noise into every layer, and networks learn far more slowly: on generated bodies
(correspondence, 1,229 vertices, 34 training bodies, every sample within r0, inner radius r0/4, 3 epochs)
test accuracy 46 % with the degree penalty against 79 % with this ``W`` (80 % with ``λ I``); with the
paper's 50 nearest samples 0.7 % against 25 % (30 %).

λ is one absolute number per surface: ``λ = ridge · median_p(trace(B_pᵀB_p) / k)``, ``ridge`` times the
typical eigenvalue of a full interior patch (≈ n_p / π for samples spread over the unit disk). The ridge
moves a coefficient by about ``λ / μ`` of the mode it sits in (``μ``: that mode's eigenvalue of
``B_pᵀB_p``), so on a well-posed patch (smallest eigenvalue ``μ_min ≫ λ``) it is negligible; where a mode
is barely seen (gaps in the sampling, few samples, boundaries) it keeps that mode's coefficient small
instead of fitting it to the samples.

The fit is computed in groups of patches with the same number of samples (no padding enters the
products): :func:`fit_groups`; :func:`fit_patches` pads the result to the widest patch.
"""

from __future__ import annotations

import numba
import numpy as np

from zernet.threads import thread_map
from zernet.zernike import num_bases, zernike_basis

from .pairs import VertexPairs, narrow_index_dtype, narrow_indptr

__all__ = ["ridge_weights", "fit_groups", "fit_patches", "carry_to_vertices"]


def ridge_weights(n_max: int) -> np.ndarray:
    """(k,) diagonal of the ridge's ``W``: 0 for the piston, 1 for every other basis (module docstring)."""
    weights = np.ones(num_bases(n_max))
    weights[0] = 0.0
    return weights


def fit_groups(
    radius: np.ndarray, angle: np.ndarray, counts: np.ndarray, n_max: int, ridge: float
) -> tuple[list, float]:
    """Fit matrices of every non-empty patch, in groups of equal patch size.

    Args:
        radius: (N, n) normalised radii ``r / r0``; the samples of patch ``p`` are its first ``counts[p]``
            columns (the rest is padding and is ignored).
        angle: (N, n) angles.
        counts: (N,) number of samples of each patch.
        n_max: highest Zernike degree (k bases).
        ridge: relative ridge (module docstring), > 0.

    Returns:
        ``(groups, lam)``: a list of ``(rows, fit)`` with ``rows`` the (g,) vertices of one patch size
        ``n`` and ``fit`` their (g, k, n) fit matrices, and the absolute λ.
    """
    k = num_bases(n_max)
    counts = np.asarray(counts, dtype=np.int64)
    groups = [(size, np.flatnonzero(counts == size)) for size in np.unique(counts) if size > 0]

    def basis_and_gram(group):
        size, rows = group
        basis_t = np.ascontiguousarray(zernike_basis(radius[rows, :size], angle[rows, :size], n_max).transpose(0, 2, 1))
        return basis_t, basis_t @ basis_t.transpose(0, 2, 1)  # (g, k, n), (g, k, k)

    # numpy releases the GIL in these products and solves: the groups are spread over threads.
    bases_and_grams = thread_map(basis_and_gram, groups)
    traces = [np.trace(gram, axis1=1, axis2=2) for _, gram in bases_and_grams]
    scale = float(np.median(np.concatenate(traces)) / k) if traces else 1.0
    lam = ridge * max(scale, 1e-12)
    penalty = lam * ridge_weights(n_max)
    diagonal = np.arange(k)

    def solve(basis_and_gram):
        basis_t, gram = basis_and_gram
        gram[:, diagonal, diagonal] += penalty
        # The inverse of each k × k matrix (symmetric positive definite; condition number at most ~1e5 on
        # a FAUST-sized body with the default ridge), then one product: about twice as fast as a solve with
        # the n samples as right-hand sides, and the same to round-off.
        return np.linalg.inv(gram) @ basis_t

    fits = thread_map(solve, bases_and_grams)
    return [(rows, fit) for (_, rows), fit in zip(groups, fits)], lam


def fit_patches(
    radius: np.ndarray, angle: np.ndarray, counts: np.ndarray, n_max: int, ridge: float
) -> tuple[np.ndarray, float]:
    """The fit matrices of :func:`fit_groups` padded into one array.

    Returns:
        ``(P, lam)``: (N, k, n) fit matrices, zero in the padding columns and for empty patches, and the
        absolute λ.
    """
    groups, lam = fit_groups(radius, angle, counts, n_max, ridge)
    fit = np.zeros((radius.shape[0], num_bases(n_max), radius.shape[1]))
    for rows, block in groups:
        fit[rows, :, : block.shape[2]] = block
    return fit, lam


def carry_to_vertices(
    groups: list, sample_index: np.ndarray, interpolation, k: int, subtract_center: bool
) -> VertexPairs:
    """The fit of every patch carried from samples to mesh vertices: ``A = blockrows_p(P_p · Interp[patch p])``,
    written as vertex pairs (:class:`zernet.operators.pairs.VertexPairs`, float64).

    Args:
        groups: ``(rows, fit)`` pairs of :func:`fit_groups`: (g,) vertices and their (g, k, n) fit matrices.
        sample_index: (N, n) sample ids of each patch (-1 for padding), nearest first.
        interpolation: (M, N) CSR, vertex values -> sample values.
        k: number of Zernike bases.
        subtract_center: also subtract ``(P_p 1) f(p)`` (the fit of ``f - f(p)``).

    Returns:
        The pairs ``(p, q)`` with ``q`` the distinct vertices ``p``'s samples interpolate from (ascending)
        and their ``k`` coefficients each. A vertex without a patch has no pairs.
    """
    n_vertices = sample_index.shape[0]
    indptr_in = interpolation.indptr.astype(np.int64)
    indices_in = interpolation.indices.astype(np.int64)
    sample_index = np.ascontiguousarray(sample_index, dtype=np.int64)

    def patch_widths(group):
        rows, block = group
        return _patch_widths(
            rows.astype(np.int64),
            sample_index[rows, : block.shape[2]],
            indptr_in,
            indices_in,
            n_vertices,
            subtract_center,
        )

    def carry(group):
        rows, block = group
        _carry(
            rows.astype(np.int64),
            np.ascontiguousarray(block),
            sample_index[rows, : block.shape[2]],
            indptr_in,
            indices_in,
            interpolation.data,
            n_vertices,
            subtract_center,
            indptr[rows],
            columns,
            values,
        )

    # The kernels release the GIL: the groups are spread over threads (each writes only its own rows).
    width = np.zeros(n_vertices, dtype=np.int64)
    for (rows, _), group_width in zip(groups, thread_map(patch_widths, groups)):
        width[rows] = group_width
    indptr = np.zeros(n_vertices + 1, dtype=np.int64)
    np.cumsum(width, out=indptr[1:])
    columns = np.empty(indptr[-1], dtype=narrow_index_dtype(max(n_vertices - 1, 0)))
    values = np.zeros((indptr[-1], k))
    thread_map(carry, groups)
    return VertexPairs(narrow_indptr(indptr), columns, values, "float64")


@numba.njit(cache=True, nogil=True)
def _patch_widths(rows, sample_index, indptr, indices, n_vertices, subtract_center):
    """(g,) number of distinct vertices the samples of each patch interpolate from (and the centre with
    ``subtract_center``)."""
    g, n = sample_index.shape
    seen = np.zeros(n_vertices, dtype=np.bool_)
    width = np.zeros(g, dtype=np.int64)
    for a in range(g):
        count = 0
        for j in range(n):
            s = sample_index[a, j]
            for t in range(indptr[s], indptr[s + 1]):
                if not seen[indices[t]]:
                    seen[indices[t]] = True
                    count += 1
        if subtract_center and not seen[rows[a]]:
            count += 1
        width[a] = count
        for j in range(n):  # reset only what this patch touched
            s = sample_index[a, j]
            for t in range(indptr[s], indptr[s + 1]):
                seen[indices[t]] = False
    return width


@numba.njit(cache=True, nogil=True)
def _carry(rows, block, sample_index, indptr, indices, data, n_vertices, subtract_center, row_start, columns, values):
    """Compiled :func:`carry_to_vertices` for one group: each patch's pairs (from ``row_start``) and their
    ``k`` values, by a dense scatter into a slot per touched vertex."""
    g, k, n = block.shape
    slot = np.full(n_vertices, -1, dtype=np.int64)
    members = np.empty(16, dtype=np.int64)
    for a in range(g):
        count = 0
        for j in range(n):
            s = sample_index[a, j]
            for t in range(indptr[s], indptr[s + 1]):
                v = indices[t]
                if slot[v] < 0:
                    slot[v] = 0
                    if count == members.shape[0]:
                        grown = np.empty(2 * count, dtype=np.int64)
                        grown[:count] = members
                        members = grown
                    members[count] = v
                    count += 1
        if subtract_center and slot[rows[a]] < 0:
            if count == members.shape[0]:
                grown = np.empty(2 * count, dtype=np.int64)
                grown[:count] = members
                members = grown
            slot[rows[a]] = 0
            members[count] = rows[a]
            count += 1
        ordered = np.sort(members[:count])
        at = row_start[a]
        for c in range(count):
            slot[ordered[c]] = c
            columns[at + c] = ordered[c]
        for j in range(n):
            s = sample_index[a, j]
            for t in range(indptr[s], indptr[s + 1]):
                c = slot[indices[t]]
                weight = data[t]
                for i in range(k):
                    values[at + c, i] += block[a, i, j] * weight
        if subtract_center:
            c = slot[rows[a]]
            for i in range(k):
                row_sum = 0.0
                for j in range(n):
                    row_sum += block[a, i, j]
                values[at + c, i] -= row_sum
        for c in range(count):
            slot[ordered[c]] = -1
