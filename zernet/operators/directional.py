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
``α_a = C_ℓ a - S_ℓ b`` and ``α_b = S_ℓ a + C_ℓ b``. :class:`DirectionalOperator` holds, per order, ``C_ℓ``
and ``S_ℓ`` as one real sparse matrix. Like the patch operator it depends on the surface only, so it is
built once per surface when the data are prepared (:func:`build_directional_operator`, or
:meth:`zernet.operators.Geometry.with_directional` for every scale of a geometry), never inside a layer.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import scipy.sparse as sp
import torch
from torch import Tensor

from zernet.fourier import fourier_dim
from zernet.geometry import transport_angles
from zernet.zernike import n_max_for

from .sparse import SparseApply, to_torch_csr

__all__ = ["DirectionalOperator", "build_directional_operator"]


class DirectionalOperator:
    r"""Transported Zernike fit of directional channels of Fourier order ``<= L``, for one surface.

    ``apply`` maps per-vertex channels ``h`` (``(N, 2L + 1, C)``, Fourier layout) to the Zernike
    coefficients of their transports into every vertex's patch, ``α[p, j, r, c]`` (module docstring).
    Order 0 needs no transport and goes through the scalar operator itself. For each order ``ℓ >= 1``
    one real sparse matrix ``phases[ℓ - 1]`` of shape ``(2 N k, N)`` interleaves ``C_ℓ = A ⊙ cos ℓγ``
    (row ``2 (p k + j)``) and ``S_ℓ = A ⊙ sin ℓγ`` (row ``2 (p k + j) + 1``); it is applied to
    ``[a_ℓ | b_ℓ]`` at once and ``α_a = C_ℓ a - S_ℓ b``, ``α_b = S_ℓ a + C_ℓ b``. Extra storage:
    ``2 L nnz(A)`` entries. Build it with :func:`build_directional_operator`.

    Attributes:
        operator: the scalar patch operator (``apply``, ``k``, ``matrix``, ``frames``).
        n_vertices: ``N``.
        k: Zernike bases per patch.
        n_max: their highest radial degree.
        order: ``L``.
        phases: list of ``L`` ``scipy.sparse.csr_matrix`` float64, ``(2 N k, N)``.
    """

    def __init__(self, operator, phases: Sequence[sp.csr_matrix]) -> None:
        self.operator = operator
        self.k = int(operator.k)
        self.n_vertices = int(operator.matrix.shape[1])
        self.n_max = n_max_for(self.k)
        self.order = len(phases)
        shape = (2 * self.n_vertices * self.k, self.n_vertices)
        for ell, m in enumerate(phases, start=1):
            if m.shape != shape:
                raise ValueError(f"phase matrix of order {ell} must be {shape}, got {m.shape}")
        self.phases = [m.tocsr() for m in phases]
        self._torch: dict = {}

    def __repr__(self) -> str:
        return f"DirectionalOperator(N={self.n_vertices}, k={self.k}, order={self.order})"

    def _tensors(self, ell: int, dtype: torch.dtype, device) -> tuple[Tensor, Tensor]:
        key = (ell, dtype, torch.device(device))
        if key not in self._torch:
            m = self.phases[ell - 1]
            self._torch[key] = (to_torch_csr(m, dtype, device), to_torch_csr(m.T.tocsr(), dtype, device))
        return self._torch[key]

    def apply(self, x: Tensor) -> Tensor:
        """``x`` ``(N, 2L + 1, C)`` -> ``(N, k, 2L + 1, C)``, in ``x``'s dtype and device, differentiable."""
        d = fourier_dim(self.order)
        n, k = self.n_vertices, self.k
        if x.dim() != 3 or x.shape[0] != n or x.shape[1] != d:
            raise ValueError(f"expected directional input ({n}, {d}, C) for order {self.order}, got {tuple(x.shape)}")
        c = x.shape[2]
        parts = [self.operator.apply(x[:, 0].contiguous()).unsqueeze(2)]
        for ell in range(1, self.order + 1):
            matrix, transpose = self._tensors(ell, x.dtype, x.device)
            ab = x[:, 2 * ell - 1 : 2 * ell + 1].reshape(n, 2 * c)  # [a_ℓ | b_ℓ]
            y = SparseApply.apply(ab, matrix, transpose).view(n, k, 2, 2, c)  # [C, S] x [a, b]
            parts.append((y[:, :, 0, 0] - y[:, :, 1, 1]).unsqueeze(2))  # α_a
            parts.append((y[:, :, 1, 0] + y[:, :, 0, 1]).unsqueeze(2))  # α_b
        return torch.cat(parts, dim=2) if len(parts) > 1 else parts[0]

    __call__ = apply

    def to(self, device) -> DirectionalOperator:
        """Move the cached torch tensors (and the scalar operator's) to ``device``; returns ``self``.

        Like :meth:`zernet.operators.PatchOperator.to`: the scipy matrices stay on the host, tensors for
        other devices are dropped.
        """
        device = torch.device(device)
        if hasattr(self.operator, "to"):
            self.operator = self.operator.to(device)
        if all(have == device for _, _, have in self._torch):
            return self
        kinds = {(ell, dtype) for ell, dtype, _ in self._torch}
        self._torch = {}
        for ell, dtype in kinds:
            self._tensors(ell, dtype, device)
        return self

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
            raise ValueError(f"cannot concatenate directional operators of different (order, k): {[(op.order, op.k) for op in ops]}")
        if operator is None:
            operator = type(ops[0].operator).concatenate([op.operator for op in ops])
        phases = [sp.block_diag([op.phases[ell] for op in ops], format="csr") for ell in range(ops[0].order)]
        return DirectionalOperator(operator, phases)


def build_directional_operator(operator, order: int) -> DirectionalOperator:
    """The :class:`DirectionalOperator` of Fourier order ``L`` of a scalar patch operator.

    A pure function of the operator (its ``matrix``, ``k`` and ``frames``; a
    :class:`~zernet.operators.PatchOperator` or a :class:`~zernet.nn.reference.MatrixOperator` with frames):
    call it once per surface when preparing the data.
    """
    fourier_dim(order)
    a = operator.matrix.tocsr()
    k = int(operator.k)
    n = int(a.shape[1])
    if order == 0:
        return DirectionalOperator(operator, [])
    frames = getattr(operator, "frames", None)
    if frames is None:
        raise ValueError("directional channels of order >= 1 need the operator's tangent frames (operator.frames)")
    frames = np.asarray(frames, dtype=np.float64)
    a.sort_indices()
    rows = np.repeat(np.arange(a.shape[0], dtype=np.int64), np.diff(a.indptr))
    cols = a.indices.astype(np.int64)
    centers = rows // k
    pairs, inverse = np.unique(centers * n + cols, return_inverse=True)
    gamma = transport_angles(frames, pairs // n, pairs % n)
    # Interleave C_ℓ and S_ℓ rows: same sparsity as A, twice the rows.
    indptr = np.zeros(2 * a.shape[0] + 1, dtype=np.int64)
    counts = np.diff(a.indptr)
    indptr[1::2] = counts
    indptr[2::2] = counts
    indptr = np.cumsum(indptr)
    row_starts = a.indptr[:-1]
    # position of every entry of A inside the interleaved arrays (cos copy; the sin copy follows its row)
    offset = np.repeat(indptr[0:-1:2] - row_starts, counts) + np.arange(a.nnz)
    indices = np.empty(2 * a.nnz, dtype=a.indices.dtype)
    indices[offset] = a.indices
    indices[offset + np.repeat(counts, counts)] = a.indices
    phases = []
    for ell in range(1, order + 1):
        angle = ell * gamma
        data = np.empty(2 * a.nnz, dtype=np.float64)
        data[offset] = a.data * np.cos(angle)[inverse.reshape(-1)]
        data[offset + np.repeat(counts, counts)] = a.data * np.sin(angle)[inverse.reshape(-1)]
        phases.append(sp.csr_matrix((data, indices, indptr), shape=(2 * a.shape[0], n)))
    return DirectionalOperator(operator, phases)
