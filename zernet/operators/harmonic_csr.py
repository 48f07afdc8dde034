r"""The CSR arrays of a directional operator's harmonic matrix and of its transpose (compiled with numba).

:meth:`zernet.operators.DirectionalOperator.apply_harmonic` multiplies by one sparse matrix ``M`` (rows
``(p, i)`` for the wanted harmonics ``i``, columns ``(q, r')``; its layout is described in
:mod:`zernet.operators.directional`) and its backward by ``Mᵀ``. On a FAUST-size surface ``M`` has about
23 M non-zeros, and a data set streamed from its cache builds it on every step, so it is written here in
two compiled passes straight into the arrays torch wraps: :func:`harmonic_csr` fills ``M`` row by row
from the scalar operator ``A``, and its transpose follows by a counting pass over the columns (rows are
visited in order, so the transpose's indices come out sorted, as scipy's ``M.T.tocsr()`` would give them).

The transport's cosines and sines are computed by numpy, once per pair and order, and only multiplied
here, so every value is bitwise the product the reference construction (``DirectionalOperator.phases``)
forms. The kernels are compiled on first use and cached on disk (``numba.njit(cache=True)``).
"""

from __future__ import annotations

import numba
import numpy as np

from .sparse import csr_transpose

__all__ = ["entry_pairs", "harmonic_csr", "csr_transpose"]


@numba.njit(cache=True, nogil=True)
def _entry_pairs_kernel(indptr, indices, k, pair_start, pair_column, out):
    """Merge each row of ``A`` (vertex ``p = row // k``) with ``p``'s sorted pairs; returns the first
    entry with no pair, or -1."""
    for row in range(indptr.shape[0] - 1):
        t, end = pair_start[row // k], pair_start[row // k + 1]
        for e in range(indptr[row], indptr[row + 1]):
            q = indices[e]
            while t < end and pair_column[t] < q:
                t += 1
            if t == end or pair_column[t] != q:
                return e
            out[e] = t
    return -1


def entry_pairs(indptr: np.ndarray, indices: np.ndarray, k: int, pairs: np.ndarray, n_vertices: int) -> np.ndarray:
    """Index into ``pairs`` of every stored entry of ``A`` (CSR arrays, sorted indices, rows ``p k + j``).

    ``pairs`` is ``(P, 2)`` sorted by ``(p, q)`` (:func:`zernet.operators.directional.patch_pairs`);
    ``ValueError`` if an entry of ``A`` has no pair.
    """
    pair_start = np.searchsorted(pairs[:, 0], np.arange(n_vertices + 1)).astype(np.int64)
    out = np.empty(len(indices), dtype=np.int64)
    missing = _entry_pairs_kernel(indptr, indices, int(k), pair_start, np.ascontiguousarray(pairs[:, 1]), out)
    if missing >= 0:
        raise ValueError("the pairs do not cover every non-zero of the operator (build them with patch_pairs)")
    return out


@numba.njit(cache=True, nogil=True)
def _fill_harmonic_kernel(
    a_indptr, a_indices, a_data, entry_pair, k, d, source_row, harmonic_r, cos, sin, indptr, indices, data
):
    n_harmonics = source_row.shape[0]
    n_vertices = (a_indptr.shape[0] - 1) // k
    for p in range(n_vertices):
        for i in range(n_harmonics):
            r = harmonic_r[i]
            src = p * k + source_row[i]
            dest = indptr[p * n_harmonics + i]
            if r == 0:  # the scalar part: A's entry at column (q, 0)
                for e in range(a_indptr[src], a_indptr[src + 1]):
                    indices[dest] = a_indices[e] * d
                    data[dest] = a_data[e]
                    dest += 1
                continue
            ell = (r + 1) // 2
            for e in range(a_indptr[src], a_indptr[src + 1]):
                value = a_data[e]
                c = cos[ell - 1, entry_pair[e]]
                s = sin[ell - 1, entry_pair[e]]
                indices[dest] = a_indices[e] * d + 2 * ell - 1
                indices[dest + 1] = a_indices[e] * d + 2 * ell
                if r % 2 == 1:  # α_a = C_ℓ a - S_ℓ b
                    data[dest] = value * c
                    data[dest + 1] = -(value * s)
                else:  # α_b = S_ℓ a + C_ℓ b
                    data[dest] = value * s
                    data[dest + 1] = value * c
                dest += 2


def harmonic_csr(a_indptr, a_indices, a_data, entry_pair, angles, k: int, order: int, harmonics, dtype=np.float64):
    """``(indptr, indices, data)`` of the harmonic matrix ``(N X, N (2L + 1))`` of ``harmonics``.

    Args:
        a_indptr, a_indices, a_data: the scalar operator ``A`` (CSR, sorted indices, ``(N k, N)``).
        entry_pair: index into the pairs of every entry of ``A`` (:func:`entry_pairs`; only read when a
            harmonic has ``r >= 1``).
        angles: ``(P,)`` transport angles of the pairs.
        k, order: coefficients per vertex and the Fourier order ``L``.
        harmonics: ``j (2L + 1) + r`` of every row block, in row order.
        dtype: of ``data`` (values are computed in float64 and rounded once).

    Indices are int32 when the matrix fits (torch's CSR products are faster with them), else int64.
    """
    d = 2 * order + 1
    harmonics = np.asarray(harmonics, dtype=np.int64)
    source_row, harmonic_r = harmonics // d, harmonics % d
    n_vertices = (len(a_indptr) - 1) // k
    # each row (p, i) repeats A's row (p, j), one entry per entry for r = 0, two for r >= 1
    row_len = np.diff(a_indptr).reshape(n_vertices, k)
    lengths = row_len[:, source_row] * np.where(harmonic_r == 0, 1, 2)
    nnz = int(lengths.sum())
    index_dtype = np.int32 if max(nnz, n_vertices * len(harmonics), n_vertices * d) < 2**31 - 1 else np.int64
    indptr = np.zeros(n_vertices * len(harmonics) + 1, dtype=index_dtype)
    np.cumsum(lengths.reshape(-1), out=indptr[1:])
    indices = np.empty(nnz, dtype=index_dtype)
    data = np.empty(nnz, dtype=dtype)
    ells = np.arange(1, order + 1, dtype=np.float64)[:, None]
    cos, sin = np.cos(ells * angles[None, :]), np.sin(ells * angles[None, :])
    if entry_pair is None:
        entry_pair = np.zeros(0, dtype=np.int64)
    _fill_harmonic_kernel(
        a_indptr, a_indices, a_data, entry_pair, int(k), d, source_row, harmonic_r, cos, sin, indptr, indices, data
    )
    return indptr, indices, data
