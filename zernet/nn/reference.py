r"""Plain rotated-kernel Zernike convolution (the paper's formulation), and a matrix-backed operator.

:func:`rotated_kernel_responses` turns the kernel explicitly to each of the ``s`` angles with
:func:`zernet.zernike.rotate_coefficients` and contracts ``s`` times, exactly as paper section 3.2.2
describes (cost linear in ``s``). It is the reference the harmonic form of :class:`~zernet.nn.conv.ZernikeConv`
is tested against, and the contraction of the "paper formulation" baseline.

:class:`MatrixOperator` applies a given sparse ``(N k) x N`` decomposition matrix; it has the interface of
:class:`zernet.operators.PatchOperator` that layers and :class:`~zernet.operators.Geometry` use (``apply``,
``k``, ``n_max``, ``n_vertices``, ``matrix``, ``to``, ``concatenate``), for tests, benchmarks, and users
who compute patch coefficients their own way.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import scipy.sparse as sp
import torch
from torch import Tensor

from zernet.operators import (
    SparseApply,
    basis_orders_of_size,
    checked_basis_order,
    reorder_basis_rows,
    to_torch_csr,
)
from zernet.operators.sparse import canonical_device
from zernet.zernike import n_max_for, rotate_coefficients

from .conv import ZernikeConv
from .pooling import angular_pool

__all__ = ["rotated_kernel_responses", "RotatedKernelConv", "MatrixOperator"]


def rotated_kernel_responses(F: Tensor, weight: Tensor, angular_resolution: int) -> Tensor:
    """Responses of the kernel turned by ``φ_a = 2π a / s``, one contraction per angle.

    Args:
        F: ``(N, k, C_in)`` coefficients.
        weight: ``(k, C_in, C_out)`` kernel ``G``.
        angular_resolution: ``s``.

    Returns:
        ``(N, s, C_out)`` with ``out[:, a] = F.reshape(N, k C_in) @ rotate_coefficients(G, φ_a, dim=0)``.
    """
    N = F.shape[0]
    C_out = weight.shape[2]
    Fm = F.reshape(N, -1)
    out = []
    for a in range(angular_resolution):
        phi = 2.0 * math.pi * a / angular_resolution
        rotated = rotate_coefficients(weight, phi, dim=0)
        out.append(Fm @ rotated.reshape(-1, C_out))
    return torch.stack(out, dim=1)


class RotatedKernelConv(ZernikeConv):
    r""":class:`~zernet.nn.conv.ZernikeConv` computed the paper's way: ``s`` explicitly rotated kernels.

    Same parameters, state dict and outputs as ``ZernikeConv`` (``pooling`` ``"max"``, ``"mean"`` or
    ``"none"``), cost linear in ``s``:

    .. math::
        \mathbf{y}_p = \operatorname{pool}_{a}\big(F_p \cdot \mathrm{Rot}(2\pi a / s)\, G\big) + \mathbf{b}.

    Shapes: ``x`` ``(N, C_in)`` -> ``(N, C_out)`` (``(N, s, C_out)`` for ``"none"``).
    """

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        if self.pooling == "continuous":
            raise ValueError("RotatedKernelConv samples s angles; continuous pooling needs ZernikeConv")

    def _plan(self):
        return None  # rotated kernels read the coefficients in the natural basis order

    def _pooled_response(self, F: Tensor, ordered: bool = False) -> Tensor:
        return angular_pool(rotated_kernel_responses(F, self.weight, self.angular_resolution), self.pooling)


class MatrixOperator:
    """A patch operator given by its matrix: ``apply(x)[p, j] = Σ_q matrix[p k + j, q] x[q]``.

    Args:
        matrix: scipy sparse (or dense numpy) array of shape ``(N k, N)``; row ``p k + j`` is coefficient
            ``j`` at vertex ``p``.
        k: number of Zernike bases (triangular: 1, 3, 6, 10, 15, 21, ...).
        frames: optional ``(N, 3, 3)`` tangent frames carried along (rows e1, e2, normal).
    """

    def __init__(self, matrix, k: int, frames: np.ndarray | None = None):
        matrix = sp.csr_matrix(matrix, dtype=np.float64)
        if matrix.shape[0] != matrix.shape[1] * k:
            raise ValueError(f"matrix must be (N*k, N) with k={k}, got {matrix.shape}")
        self.matrix = matrix
        self.k = int(k)
        self.n_max = n_max_for(self.k)
        self.n_vertices = matrix.shape[1]
        self.frames = frames
        self._cache: dict = {}

    accepts_basis_order = True  # as PatchOperator.apply

    def _tensors(self, dtype, device, basis_order=None):
        key = (dtype, canonical_device(device), basis_order)
        if key not in self._cache:
            matrix = self.matrix if basis_order is None else reorder_basis_rows(self.matrix, self.k, basis_order)
            self._cache[key] = (to_torch_csr(matrix, dtype, device), to_torch_csr(matrix.T, dtype, device))
        return self._cache[key]

    def apply(self, x: Tensor, basis_order: tuple | None = None) -> Tensor:
        """``x`` ``(N, d)`` -> ``(N, k, d)``, in ``x``'s dtype and device; ``basis_order`` as
        :meth:`zernet.operators.PatchOperator.apply`."""
        if x.dim() != 2 or x.shape[0] != self.n_vertices:
            raise ValueError(f"MatrixOperator.apply: x must be ({self.n_vertices}, d), got {tuple(x.shape)}")
        A, At = self._tensors(x.dtype, x.device, checked_basis_order(basis_order, self.k))
        return SparseApply.apply(x.contiguous(), A, At).view(self.n_vertices, self.k, x.shape[1])

    __call__ = apply

    def to(self, device, basis_orders: Sequence[tuple] = ()) -> "MatrixOperator":
        """Builds the float32 tensors of ``basis_orders`` (as :meth:`zernet.operators.PatchOperator.to`) on
        ``device``; others are built on first use (cached per dtype and device). Returns self."""
        for order in basis_orders_of_size(basis_orders, self.k):
            self._tensors(torch.float32, canonical_device(device), order)
        return self

    @staticmethod
    def concatenate(ops: Sequence["MatrixOperator"]) -> "MatrixOperator":
        """Block-diagonal operator for a batch of surfaces (vertices stacked in order)."""
        ks = {op.k for op in ops}
        if len(ks) != 1:
            raise ValueError(f"cannot concatenate operators with different k: {sorted(ks)}")
        k = ks.pop()
        frames = None
        if all(op.frames is not None for op in ops):
            frames = np.concatenate([op.frames for op in ops])
        return MatrixOperator(sp.block_diag([op.matrix for op in ops], format="csr"), k, frames)

    @classmethod
    def random(cls, n_vertices: int, k: int = 21, nnz_per_row: int = 57, seed: int = 0) -> "MatrixOperator":
        """A random sparse stand-in with ``nnz_per_row`` entries per row (for timing and tests)."""
        rng = np.random.default_rng(seed)
        rows = n_vertices * k
        nnz = min(nnz_per_row, n_vertices)
        cols = rng.integers(0, n_vertices, size=(rows, nnz))
        data = rng.standard_normal((rows, nnz)) / math.sqrt(nnz)
        m = sp.csr_matrix((data.ravel(), cols.ravel(), np.arange(0, rows * nnz + 1, nnz)), shape=(rows, n_vertices))
        m.sum_duplicates()
        return cls(m, k)

    def __repr__(self) -> str:
        return f"MatrixOperator(n_vertices={self.n_vertices}, k={self.k}, nnz={self.matrix.nnz})"
