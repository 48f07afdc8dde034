"""Reference models that zernet is measured against, in the same harness (issue 5).

Both share zernet's model signature ``model(x (N, C_in), geometry) -> (N, C_out)``, its options for widths
(``widths`` or ``task``), activation and dropout, and are registered with
:func:`zernet.nn.models.register_model`, so training, evaluation and the benchmark report select them by
name (``model.name: feastnet``) like any zernet model.

``"feastnet"`` — :class:`FeaStNet`
    Verma et al. 2018, "FeaStNet: Feature-Steered Graph Convolutions for 3D Shape Analysis", built on
    PyTorch Geometric's :class:`torch_geometric.nn.FeaStConv` (the library's layer, not a rewrite). It
    convolves over the mesh edge graph (``geometry.edge_index``) with self-loops added, as FeaStNet does.
    Settings from the FeaStNet paper's single-scale FAUST network
    (``Lin16 -> Conv32 -> Conv64 -> Conv128 -> Lin256 -> Lin(C)``): a linear input layer to 16 features
    before the first convolution, ``M = 8`` feature-steering heads, translation-invariant steering weights
    ``q_h = softmax_h(u_h^T (x_j - x_i) + c_h)`` (the variant ``FeaStConv`` implements, and the one the
    FeaStNet paper reports best on FAUST), mean aggregation over the neighbourhood including the vertex
    itself, ReLU. The convolution and linear widths are by default zernet's for the task (the ZerNet
    paper's single-scale ``(64, 128, 256, 512)`` for correspondence), so that both methods are compared at
    equal widths; ``widths=(32, 64, 128, 256)`` gives FeaStNet's own network. Dropout sits before the output
    layer, where zernet's models put it.

``"paper-zernet"`` — :class:`PaperZerNet` built from :class:`PaperZernikeConv`
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
    :class:`~zernet.nn.models.ZerNet` with every convolution swapped, with identical initial weights for the
    same seed and an interchangeable state dict. It exists to measure, in one run, what the two changes buy.

Both accept a batch of surfaces (a block-diagonal :class:`~zernet.nn.geometry.Geometry`): FeaStNet's graph
has no edges between surfaces and each patch of a concatenated operator only sees its own surface.
"""

from __future__ import annotations

import weakref
from collections.abc import Sequence

import numpy as np
import scipy.sparse
import torch
from torch import Tensor, nn
from torch_geometric.nn import FeaStConv

from zernet.patches import SparseApply, to_torch_csr

from .models import ZerNet, _activation, _resolve_widths, register_model
from .reference import RotatedKernelConv

__all__ = ["FeaStNet", "PaperZernikeConv", "PaperZerNet", "ridge_normal_matrix"]


# --------------------------------------------------------------------------------------------------
# FeaStNet
# --------------------------------------------------------------------------------------------------


@register_model("feastnet")
class FeaStNet(nn.Module):
    r"""FeaStNet (Verma et al. 2018) on PyTorch Geometric's :class:`~torch_geometric.nn.FeaStConv`.

    ``x -> [Lin(input_width), σ] -> (FeaStConv(w_i, heads), σ)_i -> Lin(widths[-1]), σ -> Dropout
    -> Lin(out_channels)``

    .. math::
        \mathbf{x}'_i = \frac{1}{|\mathcal{N}(i) \cup \{i\}|} \sum_{j \in \mathcal{N}(i) \cup \{i\}}
            \sum_{h=1}^{M} q_h(\mathbf{x}_i, \mathbf{x}_j)\, W_h \mathbf{x}_j + \mathbf{b},\qquad
        q_h = \operatorname{softmax}_h\big(\mathbf{u}_h^\top(\mathbf{x}_j - \mathbf{x}_i) + c_h\big)

    Args:
        in_channels: input features per vertex ``C_in`` (e.g. 3 for xyz).
        out_channels: outputs per vertex ``C_out`` (classes, or 1 for regression).
        widths: convolution widths followed by the hidden linear width; default from ``task`` (zernet's
            table: ``(64, 128, 256, 512)`` for correspondence). FeaStNet's own FAUST network is
            ``(32, 64, 128, 256)``.
        task: ``"correspondence"``, ``"segmentation"`` or ``"regression"``: zernet's widths for the task
            when ``widths`` is not given.
        heads: feature-steering heads ``M`` per convolution (FeaStNet: 8).
        input_width: width of the linear layer before the first convolution (FeaStNet: 16); ``None`` or
            ``0`` convolves the raw input features directly.
        activation: ``"relu"`` (FeaStNet) or ``"elu"``.
        dropout: dropout probability before the output layer (0.25, as zernet's models).
        add_self_loops: include the vertex itself in its neighbourhood (FeaStNet does).

    Shapes:
        - input: ``x`` ``(N, C_in)``; ``geometry.edge_index`` ``(2, E)`` mesh edges in both directions
          (a batch of surfaces: block-diagonal, no edges between surfaces).
        - output: ``(N, C_out)`` unnormalised scores (or regression values).
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        widths: Sequence[int] | None = None,
        task: str | None = None,
        heads: int = 8,
        input_width: int | None = 16,
        activation: str = "relu",
        dropout: float = 0.25,
        add_self_loops: bool = True,
    ) -> None:
        super().__init__()
        if int(heads) < 1:
            raise ValueError(f"heads must be >= 1, got {heads}")
        self.in_channels = int(in_channels)
        self.out_channels = int(out_channels)
        self.widths = _resolve_widths(widths, task)
        self.heads = int(heads)
        self.act = _activation(activation)
        self.input = nn.Linear(self.in_channels, int(input_width)) if input_width else None
        channels = int(input_width) if input_width else self.in_channels
        self.convs = nn.ModuleList()
        for width in self.widths[:-1]:
            self.convs.append(FeaStConv(channels, width, heads=self.heads, add_self_loops=add_self_loops))
            channels = width
        self.hidden = nn.Linear(channels, self.widths[-1])
        self.dropout = nn.Dropout(dropout)
        self.output = nn.Linear(self.widths[-1], self.out_channels)

    def reset_parameters(self) -> None:
        for module in self.modules():
            if module is not self and hasattr(module, "reset_parameters"):
                module.reset_parameters()

    def forward(self, x: Tensor, geometry) -> Tensor:
        """``x`` ``(N, C_in)``, ``geometry.edge_index`` ``(2, E)`` -> ``(N, C_out)``."""
        if x.dim() != 2 or x.shape[1] != self.in_channels:
            raise ValueError(f"FeaStNet expects x of shape (N, {self.in_channels}), got {tuple(x.shape)}")
        edge_index = getattr(geometry, "edge_index", None)
        if edge_index is None:
            raise ValueError(
                "feastnet convolves over a graph but geometry.edge_index is None: give the Geometry the mesh "
                "edges in both directions (zernet.data.preprocess.mesh_edge_index builds them, or a k-NN "
                "graph for a point cloud)"
            )
        edge_index = edge_index.to(device=x.device)
        if self.input is not None:
            x = self.act(self.input(x))
        for conv in self.convs:
            x = self.act(conv(x, edge_index))
        x = self.act(self.hidden(x))
        return self.output(self.dropout(x))


# --------------------------------------------------------------------------------------------------
# The paper's own formulation: per-layer least squares, rotated kernel copies, discrete max pooling
# --------------------------------------------------------------------------------------------------


def ridge_normal_matrix(basis: Tensor, ridge: float) -> Tensor:
    """Ridge-regularised normal matrices ``BᵀB + λ I`` of every patch's least-squares fit.

    Args:
        basis: ``(N, n, k)`` Zernike values at each patch's samples, zero rows for absent samples.
        ridge: ``λ``.

    Returns:
        ``(N, k, k)``.
    """
    gram = basis.transpose(1, 2) @ basis
    eye = torch.eye(gram.shape[-1], dtype=gram.dtype, device=gram.device)
    return gram + ridge * eye


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
    ``zernet.patches`` scales its relative ``config.ridge`` by the surface's typical patch eigenvalue), so
    ``fit(x, op)`` equals ``op.apply(x)`` to rounding and this layer equals
    :class:`~zernet.nn.conv.ZernikeConv` (same ``weight`` and ``bias``, ``pooling="max"``); pass
    ``ridge=0.01`` for the release's absolute value. A block-diagonal operator of several surfaces
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
        - input: ``x`` ``(N, C_in)``; ``operator`` a :class:`~zernet.patches.PatchOperator` of the same ``N``
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
        super().__init__(in_channels, out_channels, n_max=n_max, angular_resolution=angular_resolution,
                         pooling=pooling, bias=bias, k=k)
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
        ridge = operator.lam if self.ridge is None else self.ridge
        normal = ridge_normal_matrix(patches.basis, float(ridge))  # (N, k, k)
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


@register_model("paper-zernet")
class PaperZerNet(ZerNet):
    r"""The ZerNet paper's single-scale network with the paper's own layer (:class:`PaperZernikeConv`).

    Exactly :class:`~zernet.nn.models.ZerNet` (same options, blocks, head, initial weights for a given seed
    and state-dict keys) with every :class:`~zernet.nn.conv.ZernikeConv` replaced by a
    :class:`PaperZernikeConv` holding the same weights: per-layer least-squares fit and ``s`` rotated
    kernel copies with max pooling. The paper's ``Conv64 -> Conv128 -> Conv256 -> Lin512 -> Lin(C)`` at
    the default (correspondence) widths.

    Args:
        in_channels, out_channels, widths, task, n_max, angular_resolution, pooling, activation, dropout,
        norm, scale: as :class:`~zernet.nn.models.ZerNet` (``pooling`` ``"max"`` or ``"mean"``).
        ridge: absolute ``λ`` of the per-layer fit; ``None`` uses the operator's (see :class:`PaperZernikeConv`).

    Shapes:
        - input: ``x`` ``(N, C_in)``; ``geometry.operators[scale]`` a patch operator.
        - output: ``(N, C_out)``.
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        widths: Sequence[int] | None = None,
        task: str | None = None,
        n_max: int = 5,
        angular_resolution: int = 16,
        pooling: str = "max",
        activation: str = "relu",
        dropout: float = 0.25,
        norm: str | None = None,
        scale: int = 0,
        ridge: float | None = None,
    ) -> None:
        if pooling not in ("max", "mean"):
            raise ValueError(f"paper-zernet pools over s rotated kernels: pooling must be 'max' or 'mean', got {pooling!r}")
        super().__init__(in_channels, out_channels, widths=widths, task=task, n_max=n_max,
                         angular_resolution=angular_resolution, pooling=pooling, activation=activation,
                         dropout=dropout, norm=norm, scale=scale)
        self.ridge = ridge
        # Swap the layers without touching the global RNG, so that the weights and the later dropout draws
        # are those of ZerNet built with the same seed.
        with torch.random.fork_rng(devices=[]):
            for block in self.blocks:
                for i, conv in enumerate(block.convs):
                    paper = PaperZernikeConv(conv.in_channels, conv.out_channels, n_max=conv.n_max,
                                             angular_resolution=conv.angular_resolution, pooling=conv.pooling,
                                             bias=conv.bias is not None, ridge=ridge)
                    paper.load_state_dict(conv.state_dict())
                    block.convs[i] = paper
