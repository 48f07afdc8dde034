"""The patch operator in its compact form: vertex pairs with ``k`` values each, and the products that read it.

A patch fit's ``k`` rows of one vertex ``p`` read the same vertices ``q`` (its samples' triangle
corners), so the ``(N k) × N`` matrix ``A`` is stored once per vertex pair: the pairs ``(p, q)`` in CSR
order over ``p`` (:attr:`VertexPairs.indptr`, :attr:`VertexPairs.columns`, ``q`` ascending) and the ``k``
values of each pair, ``values[e, j] = A[p k + j, q]``. That is ``k`` times fewer indices than the CSR
matrix, and nothing is kept for the transpose: the backward reads the same pairs in the same order and
scatters into ``q`` (one output buffer per thread, summed), as fast as reading them by column on this
CPU and without the 2.7 MB column order a FAUST-size body would hold beside its pairs.

Precision (:data:`PRECISIONS`): the values are float64 as the fit computes them, or stored as float32,
float16 or bfloat16 (numpy has no bfloat16: its bit patterns are kept as uint16). Indices take the
narrowest unsigned type that holds them (uint16 up to 65,536 vertices). The products decode a 16-bit
value through a 65,536-entry float32 table (256 kB, read in cache), so the layers compute in float32 or
float64 whatever the storage.

Products (:func:`pair_product`, :func:`pair_product_transposed`): on the CPU two compiled kernels read
the compact arrays directly (each pair's ``x[q]`` is read once for its ``k`` outputs), on the run's
threads over vertex ranges (they release the GIL). On another device (CUDA) the compact tensors are
expanded there into the CSR matrix, and for a backward its transpose, for each product (:func:`expanded_csr`:
a stable sort and a few scatters, cheap on a GPU) and multiplied by :class:`zernet.operators.sparse.SparseApply`.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numba
import numpy as np
import scipy.sparse
import torch

from zernet.threads import thread_map

from .sparse import csr_from

__all__ = [
    "PRECISIONS",
    "VertexPairs",
    "PairApply",
    "pair_product",
    "pair_product_transposed",
    "expanded_csr",
    "narrow_index_dtype",
    "narrow_indptr",
]

#: Value precisions of a stored operator (``PatchConfig.precision``); ``float64`` is the fit's own.
PRECISIONS = ("float64", "float32", "float16", "bfloat16")

# The numpy dtype each precision is stored in (bfloat16 as its uint16 bit patterns).
_STORAGE = {"float64": np.float64, "float32": np.float32, "float16": np.float16, "bfloat16": np.uint16}
_TORCH = {"float64": torch.float64, "float32": torch.float32, "float16": torch.float16, "bfloat16": torch.bfloat16}


def narrow_index_dtype(largest: int) -> np.dtype:
    """The narrowest unsigned integer dtype holding ``0 .. largest``."""
    for dtype in (np.uint16, np.uint32):
        if largest <= np.iinfo(dtype).max:
            return np.dtype(dtype)
    return np.dtype(np.int64)


@functools.cache
def _decode_table(precision: str) -> np.ndarray | None:
    """float32 value of every 16-bit pattern of a half precision (``None`` for float32 / float64); one
    table per precision, shared by every operator."""
    if precision == "float16":
        return np.arange(2**16, dtype=np.uint16).view(np.float16).astype(np.float32)
    if precision == "bfloat16":  # the upper half of a float32
        return (np.arange(2**16, dtype=np.uint32) << 16).view(np.float32)
    return None


def _encode(values: np.ndarray, precision: str) -> np.ndarray:
    """float values in the storage dtype of ``precision`` (bfloat16: round to nearest even)."""
    if precision != "bfloat16":
        return np.ascontiguousarray(values, dtype=_STORAGE[precision])
    as_float = torch.from_numpy(np.ascontiguousarray(values, dtype=np.float32))
    return as_float.to(torch.bfloat16).view(torch.int16).numpy().view(np.uint16).copy()


@dataclass(eq=False)
class VertexPairs:
    """An ``(N k) × N`` patch operator matrix as vertex pairs (module docstring).

    Attributes:
        indptr: (N + 1,) the pairs of vertex ``p`` are ``indptr[p] : indptr[p + 1]``.
        columns: (P,) the vertex ``q`` of each pair, ascending within each ``p``; narrowest unsigned type.
        values: (P, k) ``values[e, j] = A[p k + j, q]`` in the storage dtype of ``precision``.
        precision: one of :data:`PRECISIONS`.
    """

    indptr: np.ndarray
    columns: np.ndarray
    values: np.ndarray
    precision: str

    def __post_init__(self) -> None:
        if self.precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {PRECISIONS}, got {self.precision!r}")
        n_pairs = int(self.indptr[-1])
        if self.values.ndim != 2 or self.values.shape[0] != n_pairs or self.columns.shape[0] != n_pairs:
            raise ValueError(
                f"vertex pairs: {self.columns.shape[0]} columns, {self.values.shape} values and "
                f"{int(self.indptr[-1])} pairs in indptr do not fit together"
            )
        if self.values.dtype != _STORAGE[self.precision]:
            raise ValueError(f"{self.precision} values are stored as {np.dtype(_STORAGE[self.precision])}")
        self._table = _decode_table(self.precision)
        # What the kernels read: half precisions as their bit patterns, decoded through the table.
        self._kernel_values = self.values if self._table is None else self.values.view(np.uint16)

    def __getstate__(self) -> dict:
        # Pickled (to and from worker processes) as the four fields: what is derived from them is rebuilt.
        return {name: getattr(self, name) for name in ("indptr", "columns", "values", "precision")}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self.__post_init__()

    @property
    def n_vertices(self) -> int:
        return int(self.indptr.shape[0] - 1)

    @property
    def k(self) -> int:
        return int(self.values.shape[1])

    @property
    def n_pairs(self) -> int:
        return int(self.columns.shape[0])

    @property
    def nbytes(self) -> int:
        """Bytes of the stored arrays."""
        return int(sum(array.nbytes for array in (self.indptr, self.columns, self.values)))

    # ------------------------------------------------------------------ conversions
    @classmethod
    def from_csr(cls, matrix: scipy.sparse.csr_matrix, k: int, precision: str = "float64") -> VertexPairs:
        """The pairs of an ``(N k) × N`` CSR matrix: each vertex's pairs are the union of the columns of its
        ``k`` rows (one k-way merge; a value a row lacks is 0)."""
        matrix = scipy.sparse.csr_matrix(matrix)
        if matrix.shape[0] != k * matrix.shape[1]:
            raise ValueError(f"a matrix of shape {matrix.shape} is not (N k, N) with k = {k}")
        if not matrix.has_sorted_indices:
            matrix = matrix.copy()
            matrix.sort_indices()
        n = matrix.shape[1]
        indptr, indices = matrix.indptr.astype(np.int64), matrix.indices.astype(np.int64)
        pair_indptr = np.zeros(n + 1, dtype=np.int64)
        _merge_rows(indptr, indices, matrix.data, k, pair_indptr, None, None)  # counts only
        np.cumsum(pair_indptr, out=pair_indptr)
        columns = np.empty(int(pair_indptr[-1]), dtype=np.int64)
        values = np.zeros((int(pair_indptr[-1]), k), dtype=np.float64)
        _merge_rows(indptr, indices, matrix.data.astype(np.float64), k, pair_indptr, columns, values)
        columns = columns.astype(narrow_index_dtype(max(n - 1, 0)))
        return cls(narrow_indptr(pair_indptr), columns, _encode(values, precision), precision)

    def with_precision(self, precision: str) -> VertexPairs:
        """The same pairs with values stored in ``precision`` (shares the index arrays)."""
        if precision == self.precision:
            return self
        return VertexPairs(self.indptr, self.columns, _encode(self.float_values(), precision), precision)

    def float_values(self) -> np.ndarray:
        """(P, k) values as float32 (half precisions decoded) or float64."""
        if self._table is not None:
            return self._table[self._kernel_values]
        return self.values

    def to_csr(self) -> scipy.sparse.csr_matrix:
        """``A`` as a scipy CSR matrix ``(N k, N)`` with sorted indices, float32 (a half precision decoded)
        or float64; a pair's zero values are kept as explicit zeros (one compiled pass, no scan)."""
        n, k = self.n_vertices, self.k
        indptr = np.zeros(n * k + 1, dtype=np.int64)
        np.cumsum(np.repeat(np.diff(self.indptr.astype(np.int64)), k), out=indptr[1:])
        dtype = np.float64 if self.precision == "float64" else np.float32
        index_dtype = np.int32 if max(n, self.n_pairs * k) < 2**31 - 1 else np.int64
        indices = np.empty(self.n_pairs * k, dtype=index_dtype)
        data = np.empty(self.n_pairs * k, dtype=dtype)
        _expand_rows(self.indptr, self.columns, self._kernel_values, self._table, indices, data)
        matrix = scipy.sparse.csr_matrix((data, indices, indptr.astype(index_dtype)), shape=(n * k, n), copy=False)
        matrix.has_sorted_indices = True
        return matrix

    def torch_arrays(self) -> dict[str, torch.Tensor]:
        """The arrays as torch tensors (copies, so they own their memory): what a device holds."""
        arrays = {"indptr": self.indptr, "columns": self.columns}
        tensors = {name: torch.from_numpy(_signed(array)) for name, array in arrays.items()}
        values = torch.from_numpy(np.array(self.values))
        tensors["values"] = values.view(torch.int16).view(torch.bfloat16) if self.precision == "bfloat16" else values
        return tensors

    @staticmethod
    def torch_nbytes(tensors: dict[str, torch.Tensor]) -> int:
        return int(sum(t.numel() * t.element_size() for t in tensors.values()))


def _signed(array: np.ndarray) -> np.ndarray:
    """An index array copied into int32, or int64 where int32 cannot hold it (torch has no unsigned indices)."""
    return np.array(array, dtype=np.int64 if array.dtype in (np.uint32, np.int64) else np.int32)


def narrow_indptr(indptr: np.ndarray) -> np.ndarray:
    """An indptr in int32 when its largest entry fits (int64 otherwise)."""
    return indptr.astype(np.int32) if indptr[-1] < 2**31 - 1 else indptr.astype(np.int64)


@numba.njit(cache=True, nogil=True)
def _merge_rows(indptr, indices, data, k, pair_indptr, columns, values):
    """Merge the sorted columns of rows ``p k .. p k + k - 1`` for every vertex ``p``. Without ``columns``
    (None) count each vertex's distinct columns into ``pair_indptr[p + 1]``; with them write the columns
    from ``pair_indptr[p]`` on and each row's value at its column (``values`` zero-filled)."""
    n = pair_indptr.shape[0] - 1
    head = np.empty(k, dtype=np.int64)
    for p in range(n):
        for j in range(k):
            head[j] = indptr[p * k + j]
        e = 0
        while True:
            smallest = -1
            for j in range(k):
                if head[j] < indptr[p * k + j + 1] and (smallest < 0 or indices[head[j]] < smallest):
                    smallest = indices[head[j]]
            if smallest < 0:
                break
            for j in range(k):
                if head[j] < indptr[p * k + j + 1] and indices[head[j]] == smallest:
                    if columns is not None:
                        values[pair_indptr[p] + e, j] = data[head[j]]
                    head[j] += 1
            if columns is not None:
                columns[pair_indptr[p] + e] = smallest
            e += 1
        if columns is None:
            pair_indptr[p + 1] = e


@numba.njit(cache=True, nogil=True)
def _expand_rows(indptr, columns, values, table, indices, data):
    """The CSR arrays of ``A``: row ``p k + j`` holds ``p``'s pairs with their ``j``-th values (decoded
    through ``table`` for a half precision)."""
    k = values.shape[1]
    dest = 0
    for p in range(indptr.shape[0] - 1):
        for j in range(k):
            for e in range(indptr[p], indptr[p + 1]):
                indices[dest] = columns[e]
                if table is None:
                    data[dest] = values[e, j]
                else:
                    data[dest] = table[values[e, j]]
                dest += 1


# ------------------------------------------------------------------------------------------ CPU products
@numba.njit(cache=True, nogil=True)
def _product_kernel(indptr, columns, values, table, order, x, out, first, last):
    """``out[p, i] += Σ_q A[p k + order[i], q] x[q]`` for ``p`` in ``first .. last - 1``."""
    k, width = order.shape[0], x.shape[1]
    for p in range(first, last):
        for e in range(indptr[p], indptr[p + 1]):
            q = columns[e]
            for i in range(k):
                if table is None:
                    v = values[e, order[i]]
                else:
                    v = table[values[e, order[i]]]
                for c in range(width):
                    out[p, i, c] += v * x[q, c]


@numba.njit(cache=True, nogil=True)
def _scatter_kernel(indptr, columns, values, table, order, grad, out, first, last):
    """``out[q] += Σ_i A[p k + order[i], q] grad[p, i]`` over the pairs ``(p, q)`` of ``p`` in ``first .. last - 1``."""
    k, width = order.shape[0], grad.shape[2]
    for p in range(first, last):
        for e in range(indptr[p], indptr[p + 1]):
            q = columns[e]
            for i in range(k):
                if table is None:
                    v = values[e, order[i]]
                else:
                    v = table[values[e, order[i]]]
                for c in range(width):
                    out[q, c] += v * grad[p, i, c]


def _vertex_ranges(parts, offsets, weights, n_chunks: int) -> list:
    """Work items ``(part, offset, first, last)``: each part's vertices cut into ranges of about equal
    ``weights`` (its pairs per vertex, cumulated), ``n_chunks`` in all."""
    total = sum(int(w[-1]) for w in weights) or 1
    items = []
    for part, offset, cumulated in zip(parts, offsets, weights):
        pieces = max(1, round(n_chunks * int(cumulated[-1]) / total))
        cuts = np.searchsorted(cumulated, np.linspace(0, cumulated[-1], pieces + 1)[1:-1])
        bounds = [0, *sorted(set(int(c) for c in cuts)), part.n_vertices]
        items += [(part, offset, a, b) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]
    return items


def _threads() -> int:
    return max(1, torch.get_num_threads())


def pair_product(parts: list[VertexPairs], x: np.ndarray, order: np.ndarray) -> np.ndarray:
    """``A x`` of the block-diagonal operator of ``parts`` (vertices stacked in order): ``x`` (N, C) float32
    or float64, returns (N, k, C) with coefficient ``i`` the basis ``order[i]``."""
    out = np.zeros((x.shape[0], order.shape[0], x.shape[1]), dtype=x.dtype)
    offsets = np.cumsum([0] + [part.n_vertices for part in parts])[:-1]
    items = _vertex_ranges(parts, offsets, [part.indptr for part in parts], 4 * _threads())

    def run(item):
        part, offset, first, last = item
        block = slice(offset, offset + part.n_vertices)
        _product_kernel(
            part.indptr, part.columns, part._kernel_values, part._table, order, x[block], out[block], first, last
        )

    thread_map(run, items, _threads())
    return out


def pair_product_transposed(parts: list[VertexPairs], grad: np.ndarray, order: np.ndarray) -> np.ndarray:
    """``Aᵀ grad`` for :func:`pair_product`'s operator: ``grad`` (N, k, C), returns (N, C). Each work item (a
    range of one part's vertices ``p``, about one per thread) scatters into its own buffer of that part's
    rows, and the buffers are summed: no two threads write the same memory."""
    out = np.zeros((grad.shape[0], grad.shape[2]), dtype=grad.dtype)
    offsets = np.cumsum([0] + [part.n_vertices for part in parts])[:-1]
    items = _vertex_ranges(parts, offsets, [part.indptr for part in parts], _threads())

    def run(item):
        part, offset, first, last = item
        block = slice(offset, offset + part.n_vertices)
        buffer = np.zeros((part.n_vertices, grad.shape[2]), dtype=grad.dtype)
        _scatter_kernel(
            part.indptr, part.columns, part._kernel_values, part._table, order, grad[block], buffer, first, last
        )
        return block, buffer

    for block, buffer in thread_map(run, items, _threads()):
        out[block] += buffer
    return out


class PairApply(torch.autograd.Function):
    """``y = A x`` (N, k, C) and ``grad_x = Aᵀ g`` on the CPU, read from the vertex pairs of ``parts``."""

    @staticmethod
    def forward(ctx, x, parts, order):
        ctx.parts, ctx.order = parts, order
        return torch.from_numpy(pair_product(parts, x.detach().numpy(), order))

    @staticmethod
    def backward(ctx, grad):
        if not ctx.needs_input_grad[0]:
            return None, None, None
        result = pair_product_transposed(ctx.parts, grad.detach().contiguous().numpy(), ctx.order)
        return torch.from_numpy(result), None, None


# ------------------------------------------------------------------------------------------ other devices
def expanded_csr(
    tensors: dict[str, torch.Tensor], k: int, n_vertices: int, dtype: torch.dtype, order, transpose: bool = True
) -> tuple:
    """``(A, Aᵀ)`` as torch CSR tensors on the tensors' device, ``A``'s rows ``p k + i`` the basis
    ``order[i]`` (:meth:`VertexPairs.torch_arrays` tensors; a few scatters of the ``P k`` values); ``Aᵀ`` is
    None unless ``transpose`` (its column order: a stable sort of the pairs by ``q``)."""
    device = tensors["values"].device
    indptr, columns = tensors["indptr"].long(), tensors["columns"].long()
    values = tensors["values"].to(dtype)[:, torch.as_tensor(order, device=device)]  # (P, k) in the asked order
    n, n_pairs = n_vertices, columns.shape[0]
    counts = indptr[1:] - indptr[:-1]
    rows_of_pairs = torch.repeat_interleave(torch.arange(n, device=device), counts)
    within = torch.arange(n_pairs, device=device) - indptr[rows_of_pairs]
    basis = torch.arange(k, device=device)
    # A: row p k + i holds p's pairs in order; entry k indptr[p] + i count_p + within
    position = (k * indptr[rows_of_pairs] + within).unsqueeze(1) + counts[rows_of_pairs].unsqueeze(1) * basis
    index_dtype = torch.int32 if n_pairs * k < 2**31 - 1 else torch.int64
    a_columns = torch.empty(n_pairs * k, dtype=index_dtype, device=device)
    a_values = torch.empty(n_pairs * k, dtype=dtype, device=device)
    a_columns[position.reshape(-1)] = columns.to(index_dtype).unsqueeze(1).expand(-1, k).reshape(-1)
    a_values[position.reshape(-1)] = values.reshape(-1)
    a_crow = torch.zeros(n * k + 1, dtype=index_dtype, device=device)
    a_crow[1:] = torch.cumsum(counts.repeat_interleave(k), 0)
    matrix = csr_from(a_crow, a_columns, a_values, (n * k, n))
    if not transpose:
        return matrix, None
    # Aᵀ: row q holds its pairs by p (stable: the pairs are stored by p), each with its k columns p k + i in order
    t_pairs = torch.sort(columns, stable=True).indices
    t_rows = rows_of_pairs[t_pairs]
    t_indptr = torch.zeros(n + 1, dtype=torch.int64, device=device)
    t_indptr[1:] = torch.cumsum(torch.bincount(columns, minlength=n), 0)
    t_crow = (k * t_indptr).to(index_dtype)
    t_columns = (t_rows.unsqueeze(1) * k + basis).to(index_dtype).reshape(-1)
    t_values = values[t_pairs].reshape(-1)
    return matrix, csr_from(t_crow, t_columns, t_values, (n, n * k))
