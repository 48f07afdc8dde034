"""Sparse products in torch with a stored transpose, and the CSR arrays they need.

Torch CSR products (directional operators, the paper baseline's sample gather, patch operators off the
CPU, :mod:`zernet.operators.pairs`) go through :class:`SparseApply`: ``torch.sparse.mm`` would re-sort
the transposed matrix on every backward pass, while a transpose built once (:func:`csr_transpose`) makes
the backward one more plain product. On the CPU a patch operator's products read its vertex pairs
directly instead (:class:`zernet.operators.pairs.PairApply`).

A matrix operator may be asked for its rows in another order within each vertex (:func:`reorder_basis_rows`:
one pass over the arrays, compiled with numba, never a sort of the whole matrix).
"""

from __future__ import annotations

import warnings

import numba
import numpy as np
import scipy.sparse
import torch

__all__ = [
    "SparseApply",
    "to_torch_csr",
    "csr_transpose",
    "checked_basis_order",
    "basis_orders_of_size",
    "reorder_basis_rows",
    "block_diagonal_csr",
    "csr_copy_to",
    "csr_from",
    "canonical_device",
]


class SparseApply(torch.autograd.Function):
    """``y = A x`` with ``grad_x = Aᵀ g``, both plain CSR products (the transpose is stored, not re-sorted).

    ``SparseApply.apply(x, A, At)`` with torch CSR tensors from :func:`to_torch_csr`; every sparse product
    in zernet goes through it (``torch.sparse.mm`` would re-sort its transpose on every backward).
    """

    @staticmethod
    def forward(ctx, x, matrix, transpose):
        ctx.transpose = transpose
        return matrix @ x

    @staticmethod
    def backward(ctx, grad):
        if not ctx.needs_input_grad[0]:
            return None, None, None
        return ctx.transpose @ grad.contiguous(), None, None


def checked_basis_order(basis_order, k: int) -> tuple | None:
    """``basis_order`` as a tuple of ints (``None`` for the identity); an error unless a permutation of k."""
    if basis_order is None:
        return None
    order = tuple(int(i) for i in basis_order)
    if sorted(order) != list(range(k)):
        raise ValueError(f"basis_order must be a permutation of range({k}), got {order}")
    return None if order == tuple(range(k)) else order


def basis_orders_of_size(basis_orders, k: int) -> set:
    """The checked orders (:func:`checked_basis_order`) among ``basis_orders`` that have ``k`` entries; a
    model's orders for other degrees (multi-scale models) are left out."""
    return {checked_basis_order(order, k) for order in basis_orders if len(order) == k}


# ------------------------------------------------------------------------------------------ CSR arrays
@numba.njit(cache=True, nogil=True)
def _transpose_kernel(indptr, indices, data, t_indptr, t_indices, t_data):
    for e in range(indices.shape[0]):  # count the entries of every column
        t_indptr[indices[e] + 1] += 1
    for column in range(t_indptr.shape[0] - 1):
        t_indptr[column + 1] += t_indptr[column]
    fill = t_indptr[:-1].copy()
    for row in range(indptr.shape[0] - 1):  # rows in order: each column's rows come out sorted
        for e in range(indptr[row], indptr[row + 1]):
            dest = fill[indices[e]]
            t_indices[dest] = row
            t_data[dest] = data[e]
            fill[indices[e]] += 1


def csr_transpose(indptr: np.ndarray, indices: np.ndarray, data: np.ndarray, n_columns: int):
    """``(indptr, indices, data)`` of the transpose of a CSR matrix with ``n_columns`` columns, sorted
    indices, in the input's index and value dtypes (a counting pass, as scipy's ``tocsc``)."""
    t_indptr = np.zeros(n_columns + 1, dtype=indptr.dtype)
    t_indices = np.empty(len(indices), dtype=indices.dtype)
    t_data = np.empty(len(data), dtype=data.dtype)
    _transpose_kernel(indptr, indices, data, t_indptr, t_indices, t_data)
    return t_indptr, t_indices, t_data


def _csr(indptr, indices, data, shape) -> scipy.sparse.csr_matrix:
    """A scipy CSR matrix over these arrays (sorted indices, no copy, no scan)."""
    matrix = scipy.sparse.csr_matrix((data, indices, indptr), shape=shape, copy=False)
    matrix.has_sorted_indices = True
    return matrix


@numba.njit(cache=True, nogil=True)
def _reorder_rows_kernel(indptr, indices, data, k, order, out_indptr, out_indices, out_data):
    dest = 0
    for p in range((indptr.shape[0] - 1) // k):
        for i in range(k):
            source = p * k + order[i]
            for e in range(indptr[source], indptr[source + 1]):
                out_indices[dest] = indices[e]
                out_data[dest] = data[e]
                dest += 1
            out_indptr[p * k + i + 1] = dest


def reorder_basis_rows(matrix: scipy.sparse.csr_matrix, k: int, basis_order) -> scipy.sparse.csr_matrix:
    """Rows of an ``(N k, ·)`` operator matrix reordered within each vertex: new row ``p k + i`` is old row
    ``p k + basis_order[i]`` (one copy of the arrays; indices stay sorted)."""
    matrix = scipy.sparse.csr_matrix(matrix)
    if matrix.shape[0] % k:
        raise ValueError(f"a matrix of {matrix.shape[0]} rows has no {k} rows per vertex")
    indptr = np.zeros_like(matrix.indptr)
    indices, data = np.empty_like(matrix.indices), np.empty_like(matrix.data)
    _reorder_rows_kernel(
        matrix.indptr, matrix.indices, matrix.data, int(k), np.asarray(basis_order, np.int64), indptr, indices, data
    )
    return _csr(indptr, indices, data, matrix.shape)


def _owned(array: np.ndarray, dtype) -> torch.Tensor:
    """A tensor over ``array`` in numpy ``dtype``; a read-only array (a mapped cache file) is copied, so the
    tensor owns its memory."""
    array = np.asarray(array).astype(dtype, copy=False)
    return torch.from_numpy(array if array.flags.writeable else array.copy())


def to_torch_csr(matrix: scipy.sparse.csr_matrix, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """scipy CSR -> torch CSR on ``device``; int32 indices when they fit (about 10 % faster products on CPU).

    The values are cast in numpy when ``dtype`` has a numpy counterpart; arrays that already have the
    index and value dtypes are shared, not copied, unless read-only (a memory-mapped cache file)."""
    matrix = scipy.sparse.csr_matrix(matrix)
    if not matrix.has_sorted_indices:
        matrix = matrix.copy()  # sort a copy: the caller's arrays may be shared with other structures
        matrix.sort_indices()
    index_dtype = np.int32 if matrix.nnz < 2**31 - 1 and max(matrix.shape) < 2**31 - 1 else np.int64
    try:
        values = _owned(matrix.data, torch.empty(0, dtype=dtype).numpy().dtype)
    except TypeError:  # no numpy counterpart (bfloat16): cast in torch
        values = _owned(matrix.data, matrix.data.dtype).to(dtype)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # "sparse CSR support is in beta"
        return torch.sparse_csr_tensor(
            _owned(matrix.indptr, index_dtype),
            _owned(matrix.indices, index_dtype),
            values,
            size=matrix.shape,
            check_invariants=False,
        ).to(device)


def canonical_device(device) -> torch.device:
    """``device`` with its index: ``cuda`` is ``cuda:<current device>``, as tensors report it (``x.device``),
    so tensors prepared for ``cuda`` are found again when a layer asks for ``x.device``."""
    device = torch.device(device)
    if device.type == "cuda" and device.index is None:
        return torch.device("cuda", torch.cuda.current_device())
    return device


def csr_from(crow: torch.Tensor, col: torch.Tensor, values: torch.Tensor, size) -> torch.Tensor:
    """A torch CSR tensor over these arrays (not checked: the callers build them sorted)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # "sparse CSR support is in beta"
        return torch.sparse_csr_tensor(crow, col, values, size=size, check_invariants=False)


def csr_copy_to(matrix: torch.Tensor, device, non_blocking: bool = False) -> torch.Tensor:
    """A torch CSR matrix on ``device`` (itself when it is there): its three arrays copied, asynchronously
    with ``non_blocking`` from pinned host memory (:func:`pinned_csr`)."""
    device = torch.device(device)
    if matrix.device == canonical_device(device):
        return matrix
    return csr_from(
        *(
            t.to(device, non_blocking=non_blocking)
            for t in (matrix.crow_indices(), matrix.col_indices(), matrix.values())
        ),
        matrix.shape,
    )


def block_diagonal_csr(matrices) -> torch.Tensor:
    """Torch CSR matrices stacked block-diagonally, on their device (one copy of their arrays, no sorting)."""
    matrices = list(matrices)
    if len(matrices) == 1:
        return matrices[0]
    nnz = sum(int(m.values().numel()) for m in matrices)
    rows = sum(m.shape[0] for m in matrices)
    cols = sum(m.shape[1] for m in matrices)
    index_dtype = torch.int32 if max(nnz, rows, cols) < 2**31 - 1 else torch.int64
    indptr, indices = [torch.zeros(1, dtype=index_dtype, device=matrices[0].device)], []
    nnz_offset = col_offset = 0
    for m in matrices:
        indptr.append(m.crow_indices()[1:].to(index_dtype) + nnz_offset)
        indices.append(m.col_indices().to(index_dtype) + col_offset)
        nnz_offset += int(m.values().numel())
        col_offset += m.shape[1]
    return csr_from(torch.cat(indptr), torch.cat(indices), torch.cat([m.values() for m in matrices]), (rows, cols))
