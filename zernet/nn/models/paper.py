r"""The ZerNet paper's own formulation as a baseline: :class:`PaperZernikeConv` and :class:`PaperZerNet`.

The ZerNet paper's own discretisation (section 3.2.2) as the authors' release runs it: at **every
layer and every step**, each vertex's patch samples are gathered from the current features
(barycentric interpolation, then the patch's sample ids), the Zernike coefficients are obtained by
re-solving the ridge-regularised least-squares problem on the ``(N, k, k)`` normal equations, the
kernel is turned to ``s`` angles ``2π a / s`` (``s`` explicitly rotated copies,
:func:`zernet.nn.reference.rotated_kernel_responses`) and the ``s`` responses are max-pooled.
It is the same map as :class:`zernet.nn.conv.ZernikeConv` with ``pooling="max"`` — zernet computes the
feature-independent fit once per surface as a sparse operator and replaces the ``s`` rotated copies by
the harmonic form — so for the same weights the outputs agree to rounding: ~1e-12 relative in float64;
in float32 the per-call solve loses about ``cond(BᵀB + λI)`` times the float32 epsilon (the fit uses
the operator's own ridge ``λ`` by default; see :class:`PaperZernikeConv`). The network is zernet's
:class:`~zernet.nn.models.ZerNet` built with this convolution instead, with identical initial weights for
the same seed and an interchangeable state dict. It exists to measure, in one run, what the two changes buy.
Since the map is the same, the paper's formulation can also be trained at zernet's speed: ``zernet`` with
``pooling: max`` on operators of the paper's 50 nearest samples (``patch_size: 50``); the weights then run
unchanged in this network (``benchmarks/speed/bench_paper_layer.py`` scores a run both ways and times both steps).

It accepts a batch of surfaces (a block-diagonal :class:`~zernet.operators.Geometry`): each patch of a
concatenated operator only sees its own surface.
"""

from __future__ import annotations

import weakref

import numpy as np
import scipy.sparse
import torch
from torch import Tensor, nn

from zernet.nn.reference import RotatedKernelConv
from zernet.operators import SparseApply, to_torch_csr

from .zernet import ZerNet, ZernikeBlock

__all__ = ["PaperZernikeConv", "PaperZerNet", "ridge_normal_matrix"]


def ridge_normal_matrix(basis: Tensor, ridge: float, weights=None) -> Tensor:
    """Ridge-regularised normal matrices ``BᵀB + λ W`` of every patch's least-squares fit.

    Args:
        basis: ``(N, n, k)`` Zernike values at each patch's samples, zero rows for absent samples.
        ridge: ``λ``.
        weights: ``(k,)`` diagonal of ``W``; ``None``: the identity (the release's plain ridge).

    Returns:
        ``(N, k, k)``.
    """
    gram = basis.transpose(1, 2) @ basis
    k = gram.shape[-1]
    diagonal = (
        torch.ones(k, dtype=gram.dtype, device=gram.device)
        if weights is None
        else torch.as_tensor(weights, dtype=gram.dtype, device=gram.device)
    )
    return gram + ridge * torch.diag(diagonal)


class _PatchTensors:
    """An operator's constant patch data on one device: the sample gather and the Zernike values.

    ``gather`` is the ``(N n, N)`` map from vertex features to the values at every patch's samples: the rows of
    ``operator.interpolation`` picked by ``patch_sample_index`` (zero rows where it is -1), minus the centre
    vertex when the operator subtracts it. It is a sparse product with a stored transpose rather than two
    index gathers, whose accumulating backward is not deterministic on CPU.
    """

    def __init__(self, operator, dtype: torch.dtype, device: torch.device) -> None:
        index = np.asarray(operator.patch_sample_index)
        n_vertices, width = index.shape
        valid = (index >= 0).ravel()
        gather = operator.interpolation.tocsr()[np.where(valid, index.ravel(), 0)]
        gather = scipy.sparse.diags(valid.astype(np.float64)) @ gather
        if getattr(operator.config, "subtract_center", False):
            rows = np.flatnonzero(valid)
            centre = scipy.sparse.csr_matrix(
                (np.ones(len(rows)), (rows, rows // width)), shape=(n_vertices * width, n_vertices)
            )
            gather = gather - centre
        gather = gather.tocsr()
        gather.eliminate_zeros()
        self.gather = to_torch_csr(gather, dtype, device)
        self.gather_t = to_torch_csr(gather.T.tocsr(), dtype, device)
        basis = np.asarray(operator.patch_basis) * (index >= 0)[..., None]
        self.basis = torch.as_tensor(basis, dtype=dtype, device=device)  # (N, n, k), 0 where no sample
        self.n_vertices = int(n_vertices)
        self.width = int(width)


# Most recently used patch tensors, shared by every PaperZernikeConv: (weakref to operator, key, tensors).
_PATCH_CACHE: list = []
_PATCH_CACHE_SIZE = 2


class PaperZernikeConv(RotatedKernelConv):
    r"""Zernike convolution as the ZerNet paper discretises it: the patch fit is re-solved at every call.

    For vertex ``p`` with patch samples ``j`` — values ``f_j`` interpolated from the vertex features
    (minus ``f_p`` when the operator was built with ``subtract_center``) and Zernike values ``B_{jk}`` —

    .. math::
        F_p = (B_p^\top B_p + \lambda I)^{-1} B_p^\top f_p \in \mathbb{R}^{k \times C_{in}},\qquad
        \mathbf{y}_p = \max_{a < s}\; F_p \cdot \mathrm{Rot}(2\pi a / s)\, G + \mathbf{b}.

    The normal equations are built from ``operator.patch_basis`` and solved with
    :func:`torch.linalg.solve` in every forward pass, like the authors' release (which uses an absolute
    ``λ = 0.01``). By default ``λ`` is the absolute value the operator was built with (``operator.lam``:
    ``zernet.operators.PatchOperator`` scales its relative ``config.ridge`` by the surface's typical patch
    eigenvalue) and ``I`` is replaced by the operator's ridge weights ``W`` (``operator.ridge_weights``: ``I`` without the piston), so
    ``fit(x, op)`` equals ``op.apply(x)`` to rounding and this layer equals
    :class:`~zernet.nn.conv.ZernikeConv` (same ``weight`` and ``bias``, ``pooling="max"``); pass
    ``ridge=0.01`` for the release's absolute value with ``I``. Build the operator with ``patch_size=50``
    (50 nearest samples) for the paper's formulation; zernet's default is every sample within ``r0``. A block-diagonal operator of several surfaces
    (``PatchOperator.concatenate``) carries a single ``lam`` (the first surface's), so in a batch of
    surfaces whose ``λ`` differ the fit of the others differs from their precomputed operator by a
    relative ``O(Δλ / eigenvalue)`` (about ``1e-3`` at most).

    The kernel contraction is :class:`~zernet.nn.reference.RotatedKernelConv`'s: ``s`` explicitly rotated
    copies of the kernel, cost linear in ``s``. Parameters, initialisation and state dict are
    :class:`~zernet.nn.conv.ZernikeConv`'s.

    Args:
        in_channels: ``C_in``.
        out_channels: ``C_out``.
        n_max: highest Zernike degree (5: ``k = 21``, the paper's); must match the operator.
        angular_resolution: ``s``, the number of rotated kernel copies.
        pooling: ``"max"`` (the paper's angular max pooling), ``"mean"`` or ``"none"``.
        bias: learn an additive bias.
        k: alternatively the number of bases (overrides ``n_max``).
        ridge: absolute ``λ`` of the fit; ``None`` takes ``operator.lam``.

    Shapes:
        - input: ``x`` ``(N, C_in)``; ``operator`` a :class:`~zernet.operators.PatchOperator` of the same ``N``
          vertices (``patch_sample_index`` ``(N, n)``, ``patch_basis`` ``(N, n, k)``, ``interpolation``
          ``(M, N)``, ``config``).
        - output: ``(N, C_out)`` (``(N, s, C_out)`` for ``pooling="none"``).
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        n_max: int = 5,
        angular_resolution: int = 16,
        pooling: str = "max",
        bias: bool = True,
        k: int | None = None,
        ridge: float | None = None,
    ) -> None:
        super().__init__(
            in_channels,
            out_channels,
            n_max=n_max,
            angular_resolution=angular_resolution,
            pooling=pooling,
            bias=bias,
            k=k,
        )
        if ridge is not None and float(ridge) < 0:
            raise ValueError(f"ridge must be >= 0, got {ridge}")
        self.ridge = None if ridge is None else float(ridge)

    @staticmethod
    def _patch_tensors(operator, dtype: torch.dtype, device: torch.device) -> _PatchTensors:
        # Constant patch data is moved to the device once per (operator, dtype, device) and shared by all
        # layers (a few recent operators are kept: training visits one surface per step); the least-squares
        # problem itself is solved again in every forward pass.
        key = (id(operator), dtype, device)
        for i, (ref, entry_key, tensors) in enumerate(_PATCH_CACHE):
            if entry_key == key and ref() is operator:
                _PATCH_CACHE.append(_PATCH_CACHE.pop(i))
                return tensors
        tensors = _PatchTensors(operator, dtype, device)
        try:
            ref = weakref.ref(operator)
        except TypeError:
            ref = lambda op=operator: op  # noqa: E731
        _PATCH_CACHE.append((ref, key, tensors))
        del _PATCH_CACHE[:-_PATCH_CACHE_SIZE]
        return tensors

    def fit(self, x: Tensor, operator) -> Tensor:
        """Zernike coefficients of every patch by ridge least squares: ``(N, C)`` -> ``(N, k, C)``."""
        if x.dim() != 2:
            raise ValueError(f"{self.__class__.__name__}: x must be (N, C), got {tuple(x.shape)}")
        if getattr(operator, "k", self.k) != self.k:
            raise ValueError(f"{self.__class__.__name__} has k={self.k} bases but the operator has k={operator.k}")
        patches = self._patch_tensors(operator, x.dtype, x.device)
        if patches.n_vertices != x.shape[0]:
            raise ValueError(f"operator covers {patches.n_vertices} vertices but x has {x.shape[0]} rows")
        # Vertex features -> values at each patch's samples (barycentric interpolation), (N, n, C).
        values = SparseApply.apply(x.contiguous(), patches.gather, patches.gather_t)
        values = values.view(patches.n_vertices, patches.width, x.shape[1])
        if self.ridge is None:  # the operator's own fit: its λ and its ridge weights
            normal = ridge_normal_matrix(patches.basis, float(operator.lam), getattr(operator, "ridge_weights", None))
        else:  # the release's plain ridge λ I
            normal = ridge_normal_matrix(patches.basis, float(self.ridge))
        rhs = patches.basis.transpose(1, 2) @ values  # (N, k, C)
        return torch.linalg.solve(normal, rhs)

    def coefficients(self, x: Tensor, operator) -> Tensor:
        """The per-call least-squares fit :meth:`fit`, checked: ``(N, k, C_in)``."""
        if x.dim() != 2 or x.shape[1] != self.in_channels:
            raise ValueError(f"{self.__class__.__name__}: x must be (N, {self.in_channels}), got {tuple(x.shape)}")
        return self.fit(x, operator)

    def __repr__(self) -> str:
        ridge = "operator" if self.ridge is None else self.ridge
        return (
            f"{self.__class__.__name__}({self.in_channels}, {self.out_channels}, n_max={self.n_max}, "
            f"k={self.k}, angular_resolution={self.angular_resolution}, pooling={self.pooling!r}, "
            f"ridge={ridge}, bias={self.bias is not None})"
        )


class PaperZerNet(ZerNet):
    r"""The ZerNet paper's single-scale network with the paper's own layer (:class:`PaperZernikeConv`).

    Exactly :class:`~zernet.nn.models.ZerNet` (same options, blocks, head, initial weights for a given seed
    and state-dict keys) with every :class:`~zernet.nn.conv.ZernikeConv` replaced by a
    :class:`PaperZernikeConv` (same parameters, drawn in the same order): per-layer least-squares fit and
    ``s`` rotated kernel copies with max pooling. The paper's ``Conv64 -> Conv128 -> Conv256 -> Lin512 ->
    Lin(C)`` at the default (correspondence) widths.

    Args:
        in_channels, out_channels, widths, task, n_max, angular_resolution, pooling, activation, dropout,
        norm, input_width, input_skip, scale: as :class:`~zernet.nn.models.ZerNet` (``pooling`` ``"max"``
        or ``"mean"``).
        ridge: absolute ``λ`` of the per-layer fit; ``None`` uses the operator's (see :class:`PaperZernikeConv`).

    Shapes:
        - input: ``x`` ``(N, C_in)``; ``geometry.operators[scale]`` a patch operator.
        - output: ``(N, C_out)``.
    """

    def init_block(
        self, index: int, in_channels: int, out_channels: int, scale: int = 0, ridge: float | None = None
    ) -> nn.Module:
        pooling = self.conv_options["pooling"]
        if pooling not in ("max", "mean"):
            raise ValueError(
                f"paper-zernet pools over s rotated kernels: pooling must be 'max' or 'mean', got {pooling!r}"
            )
        self.ridge = ridge
        return ZernikeBlock(
            in_channels,
            out_channels,
            scales=(scale,),
            activation=self.activation,
            norm=self.norm_name,
            conv=PaperZernikeConv,
            ridge=ridge,
            **self.conv_options,
        )
