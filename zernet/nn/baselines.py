"""Reference models that zernet is measured against, in the same harness (issue 5).

Two models share zernet's model signature ``model(x (N, C_in), geometry) -> (N, C_out)`` and are
registered with :func:`zernet.nn.models.register_model`, so training, evaluation and the benchmark
report select them by name like any zernet model:

``"feastnet"`` — :class:`FeaStNet`
    Verma et al. 2018, "FeaStNet: Feature-Steered Graph Convolutions for 3D Shape Analysis", built on
    PyTorch Geometric's :class:`torch_geometric.nn.FeaStConv` (the library's layer, not a rewrite).
    It convolves over the mesh edge graph (``geometry.edge_index``) with self-loops added, as FeaStNet
    does. Settings taken from the FeaStNet paper's single-scale FAUST network
    (``Lin16 -> Conv32 -> Conv64 -> Conv128 -> Lin256 -> Lin(C)``): a linear input layer to 16
    features before the first convolution, ``M = 8`` feature-steering heads, the translation-invariant
    steering weights ``softmax_h(u_h^T (x_j - x_i) + c_h)`` (the variant FeaStConv implements) and mean
    aggregation over the neighbourhood including the vertex itself. The convolution and linear widths
    are configurable: by default they are the ZerNet paper's single-scale widths
    ``(64, 128, 256, 512)`` so that the two methods are compared at equal widths; pass
    ``widths=(32, 64, 128, 256)`` for FeaStNet's own network. Activations are ReLU (FeaStNet uses
    ReLU); dropout sits before the output layer, where zernet's models put it.

``"paper-zernet"`` — :class:`PaperZerNet` built from :class:`PaperZernikeConv`
    The ZerNet paper's own discretisation (section "Discretization") as the authors' release runs it:
    at **every layer and every step** each vertex's patch samples are gathered from the current
    features (barycentric interpolation, then the patch's sample ids), the Zernike coefficients are
    obtained by re-solving a ridge-regularised least-squares problem on the ``(N, k, k)`` normal
    equations, the kernel is rotated to ``s`` discrete angles (``2π a / s``) with the ``2×2`` rotation
    of each ``±m`` coefficient pair, and the ``s`` responses are max-pooled. It is mathematically the
    same map as :class:`zernet.nn.conv.ZernikeConv` with ``pooling="max"`` — zernet only computes
    the (feature-independent) fit once per surface as a sparse operator and replaces the ``s`` rotated
    copies by the harmonic form — so its outputs agree with ZernikeConv's to float32 rounding for the
    same weights. It exists to measure, in one run, what those two changes buy.

Both models accept a batch of several surfaces (a block-diagonal :class:`~zernet.nn.geometry.Geometry`
from ``Geometry.concatenate``): FeaStNet's graph has no edges between surfaces, and every patch of a
concatenated operator only sees its own surface's samples.
"""

from __future__ import annotations

import math
import weakref
from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor, nn
from torch_geometric.nn import FeaStConv

from zernet.zernike import n_max_for, rotation_matrix

from .models import register_model

__all__ = ["FeaStNet", "PaperZernikeConv", "PaperZerNet", "ridge_normal_matrix"]


def _check_widths(widths: Sequence[int]) -> tuple[int, ...]:
    widths = tuple(int(w) for w in widths)
    if len(widths) < 2 or min(widths) < 1:
        raise ValueError(
            f"widths must list at least one convolution width and the hidden linear width, all >= 1, "
            f"e.g. (64, 128, 256, 512); got {widths}"
        )
    return widths


# --------------------------------------------------------------------------------------------------
# FeaStNet
# --------------------------------------------------------------------------------------------------


@register_model("feastnet")
class FeaStNet(nn.Module):
    r"""FeaStNet (Verma et al. 2018) on PyTorch Geometric's :class:`~torch_geometric.nn.FeaStConv`.

    ``x -> [Lin(input_width), ReLU] -> (FeaStConv(w_i, heads), ReLU)_i -> Lin(widths[-1]), ReLU
    -> Dropout -> Lin(out_channels)``

    Args:
        in_channels: input features per vertex ``C_in`` (e.g. 3 for xyz).
        out_channels: outputs per vertex ``C_out`` (classes, or 1 for regression).
        widths: convolution widths followed by the hidden linear width; default ``(64, 128, 256, 512)``
            (the ZerNet paper's single-scale correspondence network). FeaStNet's own FAUST network is
            ``(32, 64, 128, 256)``.
        heads: feature-steering heads ``M`` per convolution (FeaStNet: 8).
        input_width: width of the linear layer applied before the first convolution (FeaStNet: 16);
            ``None`` or ``0`` convolves the raw input features directly.
        dropout: dropout probability before the output layer.
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
        widths: Sequence[int] = (64, 128, 256, 512),
        heads: int = 8,
        input_width: int | None = 16,
        dropout: float = 0.25,
        add_self_loops: bool = True,
    ) -> None:
        super().__init__()
        widths = _check_widths(widths)
        if heads < 1:
            raise ValueError(f"heads must be >= 1, got {heads}")
        self.in_channels = int(in_channels)
        self.out_channels = int(out_channels)
        self.widths = widths
        self.heads = int(heads)
        self.input = nn.Linear(in_channels, input_width) if input_width else None
        channels = input_width if input_width else in_channels
        self.convs = nn.ModuleList()
        for width in widths[:-1]:
            self.convs.append(FeaStConv(channels, width, heads=heads, add_self_loops=add_self_loops))
            channels = width
        self.hidden = nn.Linear(channels, widths[-1])
        self.dropout = nn.Dropout(dropout)
        self.output = nn.Linear(widths[-1], out_channels)

    def reset_parameters(self) -> None:
        for module in self.modules():
            if module is not self and hasattr(module, "reset_parameters"):
                module.reset_parameters()

    def forward(self, x: Tensor, geometry) -> Tensor:
        """``x`` ``(N, C_in)``, ``geometry`` with ``edge_index`` ``(2, E)`` -> ``(N, C_out)``."""
        edge_index = getattr(geometry, "edge_index", None)
        if edge_index is None:
            raise ValueError(
                "feastnet convolves over mesh edges but geometry.edge_index is None: build the Geometry "
                "from a triangle mesh (point clouds have no edges; use a zernet model for them)"
            )
        edge_index = edge_index.to(device=x.device)
        if x.dim() != 2 or x.shape[1] != self.in_channels:
            raise ValueError(f"feastnet expects x of shape (N, {self.in_channels}), got {tuple(x.shape)}")
        if self.input is not None:
            x = torch.relu(self.input(x))
        for conv in self.convs:
            x = torch.relu(conv(x, edge_index))
        x = torch.relu(self.hidden(x))
        return self.output(self.dropout(x))


# --------------------------------------------------------------------------------------------------
# The paper's own formulation: per-layer least squares, rotated kernel copies, discrete max pooling
# --------------------------------------------------------------------------------------------------


def ridge_normal_matrix(basis: Tensor, valid: Tensor, ridge: float) -> Tensor:
    """Ridge-regularised normal matrices of every patch's least-squares fit.

    Args:
        basis: ``(N, n, k)`` Zernike values at each patch's samples (rows of absent samples ignored).
        valid: ``(N, n)`` bool, which samples exist.
        ridge: ``λ``; the system is ``(BᵀB + λ I) a = Bᵀ f``.

    Returns:
        ``(N, k, k)``.
    """
    b = basis * valid.unsqueeze(-1).to(basis.dtype)
    gram = b.transpose(1, 2) @ b
    eye = torch.eye(gram.shape[-1], dtype=gram.dtype, device=gram.device)
    return gram + ridge * eye


class _PatchTensors:
    """The operator's patch data (sample ids, basis values, interpolation) as tensors on one device."""

    def __init__(self, operator, dtype: torch.dtype, device: torch.device) -> None:
        index = torch.as_tensor(np.asarray(operator.patch_sample_index), dtype=torch.long)
        self.valid = (index >= 0).to(device)
        self.index = index.clamp(min=0).to(device)
        self.basis = torch.as_tensor(np.asarray(operator.patch_basis), dtype=dtype, device=device)
        interp = operator.interpolation.tocoo()
        self.interp_rows = torch.as_tensor(interp.row, dtype=torch.long, device=device)
        self.interp_cols = torch.as_tensor(interp.col, dtype=torch.long, device=device)
        self.interp_vals = torch.as_tensor(interp.data, dtype=dtype, device=device)
        self.n_samples = int(interp.shape[0])


class PaperZernikeConv(nn.Module):
    r"""Zernike convolution as the ZerNet paper discretises it, re-fitting patches at every call.

    For vertex ``p`` with patch samples ``j`` (values ``f_j`` interpolated from the vertex features,
    minus ``f_p`` when the operator was built with ``subtract_center``) and Zernike values ``B_{jk}``:

    .. math::
        F_p = (B_p^\top B_p + \lambda I)^{-1} B_p^\top f_p \in \mathbb{R}^{k \times C_{in}},\qquad
        y_p = \max_{a < s} \sum_{k, c} F_p[k, c]\,(R(2\pi a / s)\, G)[k, c, :] + b

    with ``R(φ)`` the Zernike rotation (:func:`zernet.zernike.rotation_matrix`). The fit is solved
    with :func:`torch.linalg.solve` on the ``(N, k, k)`` normal equations in every forward pass, like
    the authors' release (which uses ``λ = 0.01``); by default ``λ`` is the operator's own
    ``config.ridge`` so that the result equals zernet's precomputed operator — pass ``ridge`` to
    override.

    Args:
        in_channels: ``C_in``.
        out_channels: ``C_out``.
        k: number of Zernike bases (must match the operator's ``k``).
        rotations: angular resolution ``s`` (number of rotated kernel copies).
        ridge: ``λ``; ``None`` takes ``operator.config.ridge``.
        bias: learn an additive bias.

    Shapes:
        - input: ``x`` ``(N, C_in)``; ``operator`` a :class:`~zernet.patches.PatchOperator` over the same
          ``N`` vertices (with ``patch_sample_index``, ``patch_basis``, ``interpolation``, ``config``).
        - output: ``(N, C_out)``.
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        k: int = 21,
        rotations: int = 4,
        ridge: float | None = None,
        bias: bool = True,
    ) -> None:
        super().__init__()
        if rotations < 1:
            raise ValueError(f"rotations (angular resolution s) must be >= 1, got {rotations}")
        self.in_channels = int(in_channels)
        self.out_channels = int(out_channels)
        self.k = int(k)
        self.n_max = n_max_for(self.k)
        self.rotations = int(rotations)
        self.ridge = ridge
        self.weight = nn.Parameter(torch.empty(self.k, self.in_channels, self.out_channels))
        self.bias = nn.Parameter(torch.empty(self.out_channels)) if bias else None
        angles = torch.arange(self.rotations, dtype=torch.float64) * (2.0 * math.pi / self.rotations)
        self.register_buffer("rotation", rotation_matrix(angles, self.n_max).float(), persistent=False)
        self._patches: tuple | None = None
        self.reset_parameters()

    def reset_parameters(self) -> None:
        bound = 1.0 / math.sqrt(self.k * self.in_channels)
        nn.init.uniform_(self.weight, -bound, bound)
        if self.bias is not None:
            nn.init.zeros_(self.bias)

    def _patch_tensors(self, operator, dtype: torch.dtype, device: torch.device) -> _PatchTensors:
        # The operator's constant patch data is moved to the device once per (operator, dtype, device);
        # the least-squares solve itself is redone in every forward pass.
        if self._patches is not None:
            ref, key, tensors = self._patches
            if ref() is operator and key == (dtype, device):
                return tensors
        tensors = _PatchTensors(operator, dtype, device)
        try:
            ref = weakref.ref(operator)
        except TypeError:
            ref = lambda op=operator: op  # noqa: E731
        self._patches = (ref, (dtype, device), tensors)
        return tensors

    def fit(self, x: Tensor, operator) -> Tensor:
        """Zernike coefficients of every patch by ridge least squares: ``(N, C)`` -> ``(N, k, C)``."""
        if operator.k != self.k:
            raise ValueError(f"layer has k={self.k} Zernike bases but the operator has k={operator.k}")
        patches = self._patch_tensors(operator, x.dtype, x.device)
        n_vertices = x.shape[0]
        if patches.index.shape[0] != n_vertices:
            raise ValueError(
                f"operator covers {patches.index.shape[0]} vertices but x has {n_vertices} rows"
            )
        # Per-vertex features -> sample values (barycentric interpolation), then each patch's samples.
        samples = x.new_zeros(patches.n_samples, x.shape[1]).index_add(
            0, patches.interp_rows, x[patches.interp_cols] * patches.interp_vals.unsqueeze(1)
        )
        values = samples[patches.index]  # (N, n, C)
        if getattr(operator.config, "subtract_center", False):
            values = values - x.unsqueeze(1)
        mask = patches.valid.unsqueeze(-1).to(x.dtype)
        values = values * mask
        basis = patches.basis * mask  # (N, n, k)
        ridge = float(operator.config.ridge if self.ridge is None else self.ridge)
        normal = ridge_normal_matrix(basis, patches.valid, ridge)  # (N, k, k)
        rhs = basis.transpose(1, 2) @ values  # (N, k, C)
        return torch.linalg.solve(normal, rhs)

    def forward(self, x: Tensor, operator) -> Tensor:
        """``x`` ``(N, C_in)`` -> ``(N, C_out)``: fit, ``s`` rotated kernel copies, max over them."""
        coeffs = self.fit(x, operator)  # (N, k, C_in)
        n = coeffs.shape[0]
        rotation = self.rotation.to(dtype=x.dtype, device=x.device)  # (s, k, k)
        # Rotated kernel copies (k, C_in, s, C_out): Rot(φ_a) G for every a.
        kernels = torch.einsum("akl,lio->kiao", rotation, self.weight.to(x.dtype))
        response = coeffs.reshape(n, -1) @ kernels.reshape(self.k * self.in_channels, -1)
        out = response.view(n, self.rotations, self.out_channels).amax(dim=1)
        if self.bias is not None:
            out = out + self.bias
        return out

    def extra_repr(self) -> str:
        return (
            f"{self.in_channels}, {self.out_channels}, k={self.k}, rotations={self.rotations}, "
            f"ridge={'operator' if self.ridge is None else self.ridge}"
        )


@register_model("paper-zernet")
class PaperZerNet(nn.Module):
    r"""The ZerNet paper's single-scale network with its own layer formulation (:class:`PaperZernikeConv`).

    ``(PaperZernikeConv(w_i, s), ReLU)_i -> Lin(widths[-1]), ReLU -> Dropout -> Lin(out_channels)``,
    the paper's ``Conv64 -> Conv128 -> Conv256 -> Lin512 -> Lin(C)`` at the default widths.

    Args:
        in_channels: ``C_in``.
        out_channels: ``C_out``.
        widths: convolution widths followed by the hidden linear width.
        k: Zernike bases per patch (21 in the paper).
        rotations: angular resolution ``s`` of every convolution.
        ridge: ``λ`` of the per-layer fit; ``None`` uses the operator's (see :class:`PaperZernikeConv`).
        dropout: dropout probability before the output layer (0.25 in the authors' release).

    Shapes:
        - input: ``x`` ``(N, C_in)``; ``geometry.operators[0]`` the single-scale patch operator.
        - output: ``(N, C_out)``.
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        widths: Sequence[int] = (64, 128, 256, 512),
        k: int = 21,
        rotations: int = 4,
        ridge: float | None = None,
        dropout: float = 0.25,
    ) -> None:
        super().__init__()
        widths = _check_widths(widths)
        self.in_channels = int(in_channels)
        self.out_channels = int(out_channels)
        self.widths = widths
        channels = in_channels
        self.convs = nn.ModuleList()
        for width in widths[:-1]:
            self.convs.append(PaperZernikeConv(channels, width, k=k, rotations=rotations, ridge=ridge))
            channels = width
        self.hidden = nn.Linear(channels, widths[-1])
        self.dropout = nn.Dropout(dropout)
        self.output = nn.Linear(widths[-1], out_channels)

    def forward(self, x: Tensor, geometry) -> Tensor:
        """``x`` ``(N, C_in)``, ``geometry.operators[0]`` -> ``(N, C_out)``."""
        operator = geometry.operators[0]
        for conv in self.convs:
            x = torch.relu(conv(x, operator))
        x = torch.relu(self.hidden(x))
        return self.output(self.dropout(x))
