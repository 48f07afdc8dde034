r"""The directional operator: the patch fit of directional channels transported into each patch.

A *directional channel* at vertex ``q`` is a circle function ``h_q(ψ)`` in ``q``'s tangent plane (angle
``ψ`` from ``q``'s reference direction ``e1_q`` towards ``e2_q``), stored by its Fourier coefficients up
to order ``L`` (:mod:`zernet.fourier`).

**Transport.** ``γ_qp`` (:func:`zernet.geometry.polar.transport_angles`) is the angle, in ``p``'s frame, of ``q``'s
reference direction after the minimal rotation taking ``n_q`` onto ``n_p``: a direction at angle ``ψ`` in
``q``'s frame has angle ``ψ + γ_qp`` in ``p``'s. So in ``p``'s frame the channel of ``q`` reads
``h_q(ψ - γ_qp)``, complex coefficient ``ĥ_q(ℓ) e^{-iℓγ_qp}``; in the real layout

.. math::
    (a_\ell, b_\ell) \mapsto (a_\ell \cos \ell γ_{qp} - b_\ell \sin \ell γ_{qp},\;
                              a_\ell \sin \ell γ_{qp} + b_\ell \cos \ell γ_{qp}).

**Fit.** With ``A`` the scalar patch operator (``PatchOperator.matrix``, row ``p k + j``, column ``q``), the
Zernike coefficients of the transported channel in ``p``'s patch are, per order ``ℓ``,
``α_p(j, ℓ) = Σ_q A[(p, j), q] ĥ_q(ℓ) e^{-iℓγ_qp}``: with ``C_ℓ = A ⊙ cos ℓγ`` and ``S_ℓ = A ⊙ sin ℓγ``,
``α_a = C_ℓ a - S_ℓ b`` and ``α_b = S_ℓ a + C_ℓ b``.

**Storage and products.** :class:`DirectionalOperator` keeps only what the transport adds to ``A``: the
vertex pairs ``(p, q)`` that share a patch and their angles ``γ_qp``. A layer asks for the harmonics
``x = (j, r)`` it needs (its :class:`~zernet.nn.directional_plan.DirectionalPlan`) and
:meth:`DirectionalOperator.apply_harmonic` computes them with *one* sparse product, whose matrix (rows
``(p, x)``, columns ``(q, r')``, the transport folded in: one entry per ``A`` entry for ``r = 0``, two for
``r >= 1``) is built on first use for that set of harmonics and kept, like the patch operator's own torch
matrices. Like the patch operator it depends on the surface only, so it is built once per surface when the
data are prepared (:func:`build_directional_operator`, or :meth:`zernet.operators.Geometry.with_directional`
for every scale of a geometry), never inside a layer.

**Cost and where it is kept.** For a FAUST-size surface (6,890 vertices, 7.9 M non-zeros in ``A``, 376 k
pairs) computing the pairs and angles takes about 0.3-1.3 s, and the matrices of the ``L_out = 1`` layers
(23 M non-zeros, with their transpose about 370 MB in float32) about 0.4-0.7 s, written by the compiled
kernels of :mod:`zernet.operators.harmonic_csr` straight into the arrays torch wraps
(``benchmarks/bench_directional.py``, idle to loaded machine). A data set held in memory keeps them on its
records (:func:`zernet.inference.batch.with_directional`), so they are built once per surface, in the first
epoch; a batch of several surfaces stacks its surfaces' kept matrices (:func:`block_diagonal_csr`) instead.
A data set too large for memory (``zernet.data.preprocess.IN_MEMORY_VERTEX_LIMIT``) reads every record
back from its cache on each access, and holding the operators instead would take the memory that limit
exists to save. So the pairs and angles, which depend on the patch operator only, are kept in a file
beside the patch operator's cache file (:func:`patch_transport`, written on the first access, about 0.02 s
to read back), and only the matrices are rebuilt on every step when the shapes are not held
(``data.residency: stream``, or ``host`` on CUDA: :mod:`zernet.training.residency`).
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import scipy.sparse as sp
import torch
from torch import Tensor

from zernet.fourier import fourier_dim
from zernet.geometry import transport_angles
from zernet.zernike import n_max_for

from .cache import CacheWarning, read_arrays, write_arrays
from .harmonic_csr import entry_pairs, harmonic_csr
from .sparse import SparseApply, block_diagonal_csr, canonical_device, csr_copy_to, csr_transpose

__all__ = [
    "DirectionalOperator",
    "build_directional_operator",
    "patch_pairs",
    "patch_transport",
    "transport_cache_path",
    "block_diagonal_csr",
]


class DirectionalOperator:
    r"""Transported Zernike fit of directional channels of Fourier order ``<= L``, for one surface.

    ``apply_harmonic(x, harmonics)`` maps per-vertex channels ``h`` (``(N, 2L + 1, C)``, Fourier layout) to
    the chosen Zernike coefficients ``α[p, (j, r), c]`` of their transports into every vertex's patch
    (module docstring) in one sparse product; ``apply(x)`` returns all of them as ``(N, k, 2L + 1, C)``.
    Build it with :func:`build_directional_operator`.

    Args:
        operator: the scalar patch operator (``apply``, ``k``, ``matrix`` CSR ``(N k, N)``, ``frames``).
        order: ``L``.
        pairs: ``(P, 2)`` int vertex pairs ``(p, q)``, sorted, covering every non-zero ``A[(p, j), q]``
            (:func:`patch_pairs`).
        angles: ``(P,)`` transport angles ``γ_qp`` of the pairs.

    Attributes:
        operator, order, pairs, angles: as given; ``n_vertices`` ``N``; ``k``; ``n_max``.
        phases: per order ``ℓ = 1..L`` the interleaved ``[C_ℓ; S_ℓ]`` matrix ``(2 N k, N)`` (scipy, built on
            request: a readable reference of what :meth:`apply_harmonic` computes, not used by it).
    """

    def __init__(self, operator, order: int, pairs: np.ndarray, angles: np.ndarray) -> None:
        fourier_dim(order)
        self.operator = operator
        self.k = int(operator.k)
        self.n_vertices = int(operator.n_vertices)
        self.n_max = n_max_for(self.k)
        self.order = int(order)
        self.pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        self.angles = np.asarray(angles, dtype=np.float64).reshape(-1)
        if self.pairs.shape[0] != self.angles.shape[0]:
            raise ValueError(f"{self.pairs.shape[0]} pairs but {self.angles.shape[0]} angles")
        self._entry_pair: np.ndarray | None = None
        self._matrix: sp.csr_matrix | None = None
        self.parts: list[DirectionalOperator] = []  # the surfaces of a batch (set by concatenate)
        self._torch: dict = {}

    def __repr__(self) -> str:
        return f"DirectionalOperator(N={self.n_vertices}, k={self.k}, order={self.order}, pairs={len(self.pairs)})"

    # ------------------------------------------------------------------ matrices
    def _sorted_matrix(self) -> sp.csr_matrix:
        """The scalar operator's matrix with sorted indices, read once (a patch operator expands its pairs)."""
        if self._matrix is None:
            a = self.operator.matrix.tocsr()
            if not a.has_sorted_indices:
                a = a.copy()
                a.sort_indices()
            self._matrix = a
        return self._matrix

    def entry_pair(self) -> np.ndarray:
        """Index into :attr:`pairs` of every stored entry of ``A`` (CSR order, sorted indices), computed once."""
        if self._entry_pair is None:
            a = self._sorted_matrix()
            self._entry_pair = entry_pairs(a.indptr, a.indices, self.k, self.pairs, self.n_vertices)
        return self._entry_pair

    def _harmonic_arrays(self, harmonics: Sequence[int], dtype) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """CSR arrays ``(indptr, indices, data)`` of :meth:`harmonic_matrix`, values in numpy ``dtype``."""
        a = self._sorted_matrix()
        d = fourier_dim(self.order)
        harmonics = [int(x) for x in harmonics]
        if any(not 0 <= x < self.k * d for x in harmonics):
            raise ValueError(f"harmonics must lie in [0, {self.k * d}) for k={self.k}, L={self.order}")
        transported = any(x % d for x in harmonics)  # only these need the pair (and angle) of every entry
        return harmonic_csr(
            a.indptr,
            a.indices,
            a.data,
            self.entry_pair() if transported else None,
            self.angles,
            self.k,
            self.order,
            harmonics,
            dtype,
        )

    def harmonic_matrix(self, harmonics: Sequence[int]) -> sp.csr_matrix:
        """The matrix of :meth:`apply_harmonic`: ``(N X, N (2L + 1))``, row ``p X + i`` for harmonic
        ``harmonics[i] = j (2L + 1) + r``, column ``q (2L + 1) + r'``; float64, sorted indices.

        Row ``(p, i)`` holds, for every ``q`` of ``p``'s patch in order, ``A[(p, j), q]`` at ``r' = 0`` when
        ``r = 0``, else the two transported entries at ``r' = 2ℓ - 1, 2ℓ``
        (:func:`zernet.operators.harmonic_csr.harmonic_csr`).
        """
        n, d = self.n_vertices, fourier_dim(self.order)
        indptr, indices, data = self._harmonic_arrays(harmonics, np.float64)
        matrix = sp.csr_matrix((data, indices, indptr), shape=(n * len(harmonics), n * d))
        matrix.has_sorted_indices = True
        return matrix

    def torch_matrices(self, harmonics: Sequence[int], dtype: torch.dtype, device) -> tuple[Tensor, Tensor]:
        """The torch CSR matrix of :meth:`harmonic_matrix` and its transpose, built on first use and kept
        (per harmonics, dtype and device).

        Both are written by the compiled kernels of :mod:`zernet.operators.harmonic_csr` directly in the
        value dtype and wrapped by torch without a copy (then moved to ``device``).
        """
        harmonics = tuple(int(h) for h in harmonics)
        key = (harmonics, dtype, canonical_device(device))
        if key not in self._torch:
            if self.parts:  # a batch: the surfaces' own matrices (kept on them), stacked block-diagonally
                built = [part.torch_matrices(harmonics, dtype, device) for part in self.parts]
                self._torch[key] = tuple(block_diagonal_csr([b[i] for b in built]) for i in (0, 1))
            else:
                value_dtype = torch.empty(0, dtype=dtype).numpy().dtype
                shape = (self.n_vertices * len(harmonics), self.n_vertices * fourier_dim(self.order))
                forward = self._harmonic_arrays(harmonics, value_dtype)
                transpose = csr_transpose(*forward, shape[1])
                self._torch[key] = (_wrap_csr(forward, shape, device), _wrap_csr(transpose, shape[::-1], device))
        return self._torch[key]

    @property
    def phases(self) -> list[sp.csr_matrix]:
        if self.order == 0:
            return []
        a = self._sorted_matrix()
        gamma = self.angles[self.entry_pair()]
        counts = np.diff(a.indptr)
        indptr = np.zeros(2 * a.shape[0] + 1, dtype=np.int64)
        indptr[1::2], indptr[2::2] = counts, counts
        indptr = np.cumsum(indptr)
        offset = np.repeat(indptr[0:-1:2] - a.indptr[:-1], counts) + np.arange(a.nnz)
        indices = np.empty(2 * a.nnz, dtype=a.indices.dtype)
        indices[offset] = indices[offset + np.repeat(counts, counts)] = a.indices
        out = []
        for ell in range(1, self.order + 1):
            data = np.empty(2 * a.nnz)
            data[offset] = a.data * np.cos(ell * gamma)
            data[offset + np.repeat(counts, counts)] = a.data * np.sin(ell * gamma)
            out.append(sp.csr_matrix((data, indices, indptr), shape=(2 * a.shape[0], self.n_vertices)))
        return out

    # ------------------------------------------------------------------ apply
    def apply_harmonic(self, x: Tensor, harmonics: Sequence[int]) -> Tensor:
        """The harmonics ``x = j (2L + 1) + r`` of the transported fit, in one sparse product.

        Args:
            x: ``(N, 2L + 1, C)`` channels in the Fourier layout.
            harmonics: the wanted ``(j, r)`` as ``j (2L + 1) + r`` (a layer's ``plan.inputs``).

        Returns:
            ``(N, len(harmonics), C)`` in ``x``'s dtype and device, differentiable.
        """
        d = fourier_dim(self.order)
        n = self.n_vertices
        if x.dim() != 3 or x.shape[0] != n or x.shape[1] != d:
            raise ValueError(f"expected directional input ({n}, {d}, C) for order {self.order}, got {tuple(x.shape)}")
        harmonics = tuple(int(h) for h in harmonics)
        matrix, transpose = self.torch_matrices(harmonics, x.dtype, x.device)
        c = x.shape[2]
        out = SparseApply.apply(x.reshape(n * d, c).contiguous(), matrix, transpose)
        return out.view(n, len(harmonics), c)

    def apply(self, x: Tensor) -> Tensor:
        """``x`` ``(N, 2L + 1, C)`` -> every coefficient ``(N, k, 2L + 1, C)``, differentiable."""
        d = fourier_dim(self.order)
        return self.apply_harmonic(x, range(self.k * d)).view(self.n_vertices, self.k, d, x.shape[-1])

    __call__ = apply

    def to(self, device) -> DirectionalOperator:
        """Move the cached torch tensors (and the scalar operator's) to ``device``; returns ``self``.

        Like :meth:`zernet.operators.PatchOperator.to`: the numpy data stay on the host, tensors for other
        devices are dropped.
        """
        device = canonical_device(device)
        if hasattr(self.operator, "to"):
            self.operator = self.operator.to(device)
        if all(have == device for _, _, have in self._torch):
            return self
        kinds = {(harmonics, dtype) for harmonics, dtype, _ in self._torch}
        self._torch = {}
        for harmonics, dtype in kinds:
            self.torch_matrices(harmonics, dtype, device)
        return self

    def copy_to(self, device, non_blocking: bool = False, operator=None) -> DirectionalOperator:
        """A copy whose torch matrices (and its scalar operator's) are on ``device``; this one keeps its own
        (a host-resident record copied for one step, :mod:`zernet.training.residency`). ``operator``: the
        scalar operator's copy when the caller has made it already."""
        device = canonical_device(device)
        copy = DirectionalOperator.__new__(DirectionalOperator)
        copy.__dict__.update(self.__dict__)
        if operator is None and hasattr(self.operator, "copy_to"):
            operator = self.operator.copy_to(device, non_blocking)
        copy.operator = self.operator if operator is None else operator
        copy.parts = [part.copy_to(device, non_blocking) for part in self.parts]
        copy._torch = {
            (harmonics, dtype, device): tuple(csr_copy_to(m, device, non_blocking) for m in matrices)
            for (harmonics, dtype, _), matrices in self._torch.items()
        }
        return copy

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_torch"] = {}  # torch tensors are rebuilt on demand after unpickling
        return state

    @staticmethod
    def concatenate(ops: Sequence[DirectionalOperator], operator=None) -> DirectionalOperator:
        """Block-diagonal operator of several surfaces (vertices stacked in order), like
        :meth:`zernet.operators.PatchOperator.concatenate`.

        Args:
            ops: directional operators of the same order and ``k``.
            operator: the already concatenated scalar operator of the same surfaces (a batch has it in
                ``Geometry.operators``); ``None`` concatenates the ``ops``' own.
        """
        ops = list(ops)
        if not ops:
            raise ValueError("concatenate needs at least one directional operator")
        if len({(op.order, op.k) for op in ops}) != 1:
            raise ValueError(
                f"cannot concatenate directional operators of different (order, k): {[(op.order, op.k) for op in ops]}"
            )
        if operator is None:
            operator = type(ops[0].operator).concatenate([op.operator for op in ops])
        offsets = np.cumsum([0] + [op.n_vertices for op in ops])[:-1]
        pairs = np.concatenate([op.pairs + off for op, off in zip(ops, offsets)])
        batch = DirectionalOperator(operator, ops[0].order, pairs, np.concatenate([op.angles for op in ops]))
        # Products reuse the surfaces' matrices (built once per surface and kept on it), stacked per step.
        batch.parts = [part for op in ops for part in (op.parts or [op])]
        return batch


def _wrap_csr(arrays: tuple[np.ndarray, np.ndarray, np.ndarray], shape: tuple[int, int], device) -> Tensor:
    """Torch CSR tensor over numpy CSR arrays (no copy on the CPU), on ``device``."""
    indptr, indices, data = (torch.from_numpy(array) for array in arrays)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # "sparse CSR support is in beta"
        return torch.sparse_csr_tensor(indptr, indices, data, size=shape, check_invariants=False).to(device)


def patch_pairs(matrix: sp.csr_matrix, k: int) -> np.ndarray:
    """The sorted vertex pairs ``(p, q)`` with a non-zero ``A[(p, j), q]`` for some ``j``: ``(P, 2)`` int64.

    Fast when every row of a vertex has the same columns (a patch fit: all ``k`` rows read the same
    vertices); any other pattern is handled by a sort.
    """
    a = matrix.tocsr()
    if not a.has_sorted_indices:
        a = a.copy()
        a.sort_indices()
    n = a.shape[1]
    row_len = np.diff(a.indptr).reshape(-1, k)
    first = row_len[:, 0]
    if np.all(row_len == first[:, None]):  # each vertex's k rows are one (k, n_p) block of the CSR arrays
        vertex = np.repeat(np.arange(len(first), dtype=np.int64), k * first)
        starts = a.indptr[: len(first) * k : k]
        within = np.arange(a.nnz) - starts[vertex]
        column = within % np.maximum(first[vertex], 1)
        if np.array_equal(a.indices, a.indices[starts[vertex] + column]):
            in_first_row = within < first[vertex]
            return np.stack([vertex[in_first_row], a.indices[in_first_row].astype(np.int64)], axis=1)
    centers = np.repeat(np.arange(a.shape[0], dtype=np.int64) // k, np.diff(a.indptr))
    keys = np.unique(centers * n + a.indices)
    return np.stack([keys // n, keys % n], axis=1)


def patch_transport(operator) -> tuple[np.ndarray, np.ndarray]:
    """The vertex pairs of a patch operator (:func:`patch_pairs`) and their transport angles ``γ_qp``.

    They depend on the scalar operator only (not on the order ``L``). When the operator was read from or
    written to the operator cache (its ``cache_file``, set by :func:`zernet.operators.build_patch_operator`),
    they are kept in a checked file beside it (:func:`transport_cache_path`): a data set streamed from its
    cache rebuilds the operator on every access, and reads them back instead of computing them again. A
    file that cannot be trusted is rebuilt with a :class:`~zernet.operators.cache.CacheWarning`.
    """
    cache_file = getattr(operator, "cache_file", None)
    path = None if cache_file is None else transport_cache_path(cache_file)
    key = None if path is None else f"{Path(cache_file).stem}:transport"
    if path is not None and path.exists():
        try:
            arrays, _ = read_arrays(path, key=key)
            pairs, angles = arrays["pairs"].astype(np.int64), arrays["angles"]
            n = int(operator.n_vertices)
            if (
                pairs.ndim != 2
                or pairs.shape[1] != 2
                or angles.shape != (len(pairs),)
                or (pairs.size and pairs.max() >= n)
            ):
                raise ValueError(f"{path}: pairs {pairs.shape} and angles {angles.shape} do not fit {n} vertices")
            return pairs, angles
        except (ValueError, KeyError, OSError) as error:
            warnings.warn(f"rebuilding cached transport angles {path}: {error}", CacheWarning, stacklevel=2)
    frames = getattr(operator, "frames", None)
    if frames is None:
        raise ValueError("directional channels of order >= 1 need the operator's tangent frames (operator.frames)")
    pairs = patch_pairs(operator.matrix, int(operator.k))
    angles = transport_angles(np.asarray(frames, dtype=np.float64), pairs[:, 0], pairs[:, 1])
    if path is not None:
        index_dtype = np.int32 if operator.n_vertices < 2**31 else np.int64  # half the file
        try:
            write_arrays(path, {"pairs": pairs.astype(index_dtype), "angles": angles}, key=key)
        except OSError as error:  # a read-only cache still works, it just recomputes them
            warnings.warn(f"could not cache transport angles at {path}: {error}", CacheWarning, stacklevel=2)
    return pairs, angles


def transport_cache_path(cache_file: str | os.PathLike) -> Path:
    """The file of the pairs and transport angles of the operator cached in ``cache_file``."""
    cache_file = Path(cache_file)
    return cache_file.with_name(f"{cache_file.stem}.transport.zop")


def build_directional_operator(operator, order: int) -> DirectionalOperator:
    """The :class:`DirectionalOperator` of Fourier order ``L`` of a scalar patch operator.

    A pure function of the operator (its ``matrix``, ``k`` and ``frames``; a
    :class:`~zernet.operators.PatchOperator` or a :class:`~zernet.nn.reference.MatrixOperator` with frames):
    call it once per surface when preparing the data. Only the pairs and their transport angles are
    needed here (:func:`patch_transport`, read from the operator cache when the operator came from it);
    each layer's sparse matrix is built on its first product and kept.
    """
    fourier_dim(order)
    if order == 0:
        return DirectionalOperator(operator, 0, np.zeros((0, 2), np.int64), np.zeros(0))
    pairs, gamma = patch_transport(operator)
    return DirectionalOperator(operator, order, pairs, gamma)
