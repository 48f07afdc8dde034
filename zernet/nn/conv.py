r"""The Zernike convolution layer, computed through the harmonic form.

At vertex :math:`p` the input channels are decomposed on the tangent disk, :math:`F_p \in \mathbb{R}^{k \times C_{in}}`
(``operator.apply(x)``). A kernel is :math:`G \in \mathbb{R}^{k \times C_{in} \times C_{out}}`; rotating it by
:math:`\varphi` turns each pair of coefficients :math:`(n, \pm m)` by :math:`m\varphi`
(:func:`zernet.zernike.rotate_coefficients`), and the convolution is a dot product of coefficients
(paper eq. 10):

.. math::
    \mathrm{resp}_p(\varphi) = \sum_{j, c} F_p[j, c]\, \big(\mathrm{Rot}(\varphi) G\big)[j, c, :]
        = A_0 + \sum_{m=1}^{n_{max}} A_m \cos m\varphi + B_m \sin m\varphi,

with, summing over the pairs ``(c_j, s_j)`` = (cosine, sine) basis indices of order ``m``,

.. math::
    A_0 = \sum_{m_j = 0} F_j G_j, \qquad
    A_m = \sum F_{c} G_{c} + F_{s} G_{s}, \qquad
    B_m = \sum F_{c} G_{s} - F_{s} G_{c}.

Each basis row contributes to at most two outputs, so all harmonics cost about ``2 k C_in C_out`` per vertex
(``39 / 21`` of one unrotated contraction for ``n_max = 5``) whatever ``s`` is. At ``s`` equispaced angles
``φ_a = 2π a / s``, frequencies alias (``cos(mφ_a) = cos((m mod s) φ_a)``), so the layer folds them to degree
``min(n_max, ⌊s/2⌋)`` first (:func:`harmonic_plan`): ``s = 1`` is exactly one unrotated contraction, ``s = 2``
costs the same, ``s = 4`` costs ``33 / 21``. Continuous pooling uses the unfolded polynomial.

The harmonic form is exposed for other layers (:mod:`zernet.nn.directional`): :func:`harmonic_plan`,
:func:`harmonic_contraction`, and the pooling helpers in :mod:`zernet.nn.pooling`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache, wraps

import numpy as np
import torch
from torch import Tensor, nn

from zernet.zernike import harmonic_pairs, n_max_for, num_bases, orders

from .pooling import POOLING_MODES, continuous_max, discrete_max, equispaced_angles, evaluate_harmonics

__all__ = ["HarmonicPlan", "harmonic_plan", "harmonic_contraction", "ZernikeConv", "float32_forward"]


def float32_forward(forward):
    """Decorate a surface convolution's ``forward(self, x, operator)`` to run in float32 under ``torch.autocast``.

    Mixed precision (``train.precision: bfloat16``) speeds up the linear layers; the patch operators are
    sparse float32 matrices without bfloat16 kernels, and the Zernike fits of boundary patches need float32's
    precision, so convolutions take their input as float32 and return float32 whatever the autocast state.
    """

    @wraps(forward)
    def wrapped(self, x: Tensor, *args, **kwargs):
        if not torch.is_autocast_enabled(x.device.type):
            return forward(self, x, *args, **kwargs)
        with torch.autocast(x.device.type, enabled=False):
            return forward(self, x.float(), *args, **kwargs)

    return wrapped


@dataclass(frozen=True)
class HarmonicPlan:
    """How a kernel's rows map onto the harmonics ``A_f, B_f`` (a fixed rearrangement of ``G``).

    Attributes:
        n_max: radial degree of the basis (``k = num_bases(n_max)``).
        angular_resolution: ``s`` the harmonics are folded for, or ``None`` for the true polynomial.
        degree: ``D``, the output has ``2 D + 1`` slabs (harmonic layout of :mod:`zernet.nn.pooling`).
        perm: ``(k,)`` basis rows reordered so each frequency's rows are contiguous (ascending frequency).
        groups: per frequency ``f = 0..D``, the ``[start, stop)`` range of its rows in ``perm`` order.
        has_sin: per frequency, whether ``B_f`` is computed (false for ``f = 0`` and for ``f = s / 2``,
            where ``sin(f φ_a) = 0`` at every sample angle; that slab is zero).
        partner: ``(k,)`` in ``perm`` order, the row of ``G`` whose values feed ``B_f`` for this row
            (the other member of its ``±m`` pair); ``sign``: ``(k,)`` the factor (``±1``, 0 if none).
        identity: ``perm`` is the identity (no gather needed).
    """

    n_max: int
    angular_resolution: int | None
    degree: int
    perm: tuple
    groups: tuple
    has_sin: tuple
    partner: tuple
    sign: tuple
    identity: bool


@lru_cache(maxsize=None)
def harmonic_plan(n_max: int, angular_resolution: int | None = None, mean_only: bool = False) -> HarmonicPlan:
    """Build the rearrangement of a kernel into harmonics.

    Args:
        n_max: radial degree of the Zernike basis.
        angular_resolution: ``s`` to fold aliased frequencies for sampling at ``2π a / s``; ``None`` keeps
            the true trigonometric polynomial of degree ``n_max`` (needed for continuous pooling).
        mean_only: only ``A_0`` (the mean over the ``s`` angles): the rows whose order is ``0 mod s``.

    Returns:
        A :class:`HarmonicPlan` (cached).
    """
    s = angular_resolution
    if s is not None and s < 1:
        raise ValueError(f"angular resolution must be >= 1, got {s}")
    m_signed = orders(n_max)
    zero, ci, si, _ = harmonic_pairs(n_max)
    k = num_bases(n_max)
    partner_of = np.full(k, -1)
    partner_of[ci], partner_of[si] = si, ci
    freq = np.empty(k, dtype=np.int64)
    fold_sign = np.ones(k, dtype=np.int64)  # sin(|m| φ_a) = fold_sign * sin(f φ_a)
    sin_on = np.zeros(k, dtype=bool)
    for j in range(k):
        a = abs(int(m_signed[j]))
        if s is None:
            f, sg = a, 1
        else:
            r = a % s
            f, sg = (s - r, -1) if 2 * r > s else (r, 1)
        freq[j], fold_sign[j] = f, sg
        sin_on[j] = f > 0 and (s is None or 2 * f != s)
    rows = np.arange(k)
    if mean_only:
        rows = rows[freq == 0]
    degree = int(freq[rows].max()) if len(rows) else 0
    perm, groups, has_sin = [], [], []
    for f in range(degree + 1):
        members = rows[freq[rows] == f]
        groups.append((len(perm), len(perm) + len(members)))
        perm.extend(int(j) for j in members)
        has_sin.append(bool(len(members)) and bool(sin_on[members].all()))
    partner, sign = [], []
    for j in perm:
        if sin_on[j]:
            # B_f = Σ F_c (σ G_s) + F_s (-σ G_c): cosine rows (m > 0) take +σ G_partner, sine rows -σ G_partner
            partner.append(int(partner_of[j]))
            sign.append(int(fold_sign[j]) * (1 if m_signed[j] > 0 else -1))
        else:
            partner.append(j)
            sign.append(0)
    return HarmonicPlan(
        n_max=n_max,
        angular_resolution=s,
        degree=degree,
        perm=tuple(perm),
        groups=tuple(groups),
        has_sin=tuple(has_sin),
        partner=tuple(partner),
        sign=tuple(sign),
        identity=perm == list(range(k)),
    )


class _HarmonicContraction(torch.autograd.Function):
    """``F (N, k, C_in)``, ``G (k, C_in, C_out)`` -> ``H (2 D + 1, N, C_out)``; per-frequency matmuls on views."""

    @staticmethod
    def forward(ctx, F: Tensor, G: Tensor, plan: HarmonicPlan, ordered: bool) -> Tensor:
        N, k_in, C_in = F.shape
        k = len(plan.perm)
        C_out = G.shape[2]
        dev = F.device
        perm = torch.as_tensor(plan.perm, device=dev)
        if plan.identity or ordered:  # F's basis rows are already in plan.perm order
            X = F.reshape(N, k * C_in)
        else:
            X = F.index_select(1, perm).view(N, k * C_in)
        WA, WB = _plan_weights(G, plan, perm)
        H = torch.empty(2 * plan.degree + 1, N, C_out, dtype=F.dtype, device=dev)
        for f, (a, b) in enumerate(plan.groups):
            cols = slice(a * C_in, b * C_in)
            slab_a = 0 if f == 0 else 2 * f - 1
            if a == b:
                H[slab_a].zero_()
            else:
                torch.mm(X[:, cols], WA[cols], out=H[slab_a])
            if f > 0:
                if plan.has_sin[f]:
                    torch.mm(X[:, cols], WB[cols], out=H[2 * f])
                else:
                    H[2 * f].zero_()
        ctx.plan = plan
        ctx.k_in = k_in
        ctx.ordered = ordered
        ctx.save_for_backward(X, G, WA, WB)
        return H

    @staticmethod
    def backward(ctx, dH: Tensor):
        X, G, WA, WB = ctx.saved_tensors
        plan: HarmonicPlan = ctx.plan
        dH = dH.contiguous()
        N = X.shape[0]
        k_in, C_in, C_out = G.shape
        k = len(plan.perm)
        dev = X.device
        perm = torch.as_tensor(plan.perm, device=dev)
        dF = dG = None
        if ctx.needs_input_grad[0]:
            dX = torch.empty(N, k * C_in, dtype=X.dtype, device=dev)
            for f, (a, b) in enumerate(plan.groups):
                if a == b:
                    continue
                cols = slice(a * C_in, b * C_in)
                slab_a = 0 if f == 0 else 2 * f - 1
                view = dX[:, cols]
                torch.mm(dH[slab_a], WA[cols].t(), out=view)
                if f > 0 and plan.has_sin[f]:
                    view.addmm_(dH[2 * f], WB[cols].t())
            if plan.identity or ctx.ordered:
                dF = dX.view(N, k, C_in)
            elif k == ctx.k_in:  # a permutation: gather back instead of zero-fill and scatter
                inverse = torch.empty_like(perm)
                inverse[perm] = torch.arange(k, device=dev)
                dF = dX.view(N, k, C_in).index_select(1, inverse)
            else:
                dF = torch.zeros(N, ctx.k_in, C_in, dtype=X.dtype, device=dev)
                dF.index_copy_(1, perm, dX.view(N, k, C_in))
        if ctx.needs_input_grad[1]:
            dWA = torch.empty(k * C_in, C_out, dtype=X.dtype, device=dev)  # every row belongs to a group
            dWB = torch.empty(k * C_in, C_out, dtype=X.dtype, device=dev)
            for f, (a, b) in enumerate(plan.groups):
                if a == b:
                    continue
                cols = slice(a * C_in, b * C_in)
                slab_a = 0 if f == 0 else 2 * f - 1
                torch.mm(X[:, cols].t(), dH[slab_a], out=dWA[cols])
                if f > 0 and plan.has_sin[f]:  # other rows of dWB are never read (their sign is 0)
                    torch.mm(X[:, cols].t(), dH[2 * f], out=dWB[cols])
            # Row by row: index_add_ over the basis axis is tens of times slower than these k small adds.
            dG = torch.zeros_like(G)
            dWA, dWB = dWA.view(k, C_in, C_out), dWB.view(k, C_in, C_out)
            for i, (row, partner, sign) in enumerate(zip(plan.perm, plan.partner, plan.sign)):
                dG[row].add_(dWA[i])
                if sign:
                    dG[partner].add_(dWB[i], alpha=sign)
        return dF, dG, None, None


def _plan_weights(G: Tensor, plan: HarmonicPlan, perm: Tensor) -> tuple[Tensor, Tensor]:
    """Stacked weights ``(k C_in, C_out)`` for the ``A`` and ``B`` harmonics, rows in ``plan.perm`` order."""
    k = len(plan.perm)
    C_in, C_out = G.shape[1], G.shape[2]
    WA = G.reshape(-1, C_out) if plan.identity else G.index_select(0, perm).reshape(k * C_in, C_out)
    partner = torch.as_tensor(plan.partner, device=G.device)
    sign = torch.as_tensor(plan.sign, dtype=G.dtype, device=G.device).view(k, 1, 1)
    WB = (G.index_select(0, partner) * sign).reshape(k * C_in, C_out)
    return WA, WB


def harmonic_contraction(F: Tensor, weight: Tensor, plan: HarmonicPlan, ordered: bool = False) -> Tensor:
    """All harmonics of the rotated-kernel response in one pass.

    Args:
        F: ``(N, k, C_in)`` Zernike coefficients of the input channels (``operator.apply(x)``).
        weight: ``(k, C_in, C_out)`` kernel ``G`` (basis rows in the natural order).
        plan: from :func:`harmonic_plan` (``plan.n_max`` must match ``k``).
        ordered: ``F``'s basis rows are already in ``plan.perm`` order
            (``operator.apply(x, basis_order=plan.perm)``), so no gather is needed; only for plans that
            keep every row.

    Returns:
        ``H`` of shape ``(2 D + 1, N, C_out)`` in the harmonic layout of :mod:`zernet.nn.pooling`
        (``D = plan.degree``). With ``plan.angular_resolution = s``, ``evaluate_harmonics(H, 2π a / s)``
        equals the response of the kernel rotated by ``2π a / s``; with ``None`` it is the true polynomial.
    """
    if F.dim() != 3 or weight.dim() != 3 or F.shape[1] != weight.shape[0] or F.shape[2] != weight.shape[1]:
        raise ValueError(
            f"harmonic_contraction: F must be (N, k, C_in) and weight (k, C_in, C_out), got {tuple(F.shape)} "
            f"and {tuple(weight.shape)}"
        )
    if F.shape[1] != num_bases(plan.n_max):
        raise ValueError(f"plan is for n_max={plan.n_max} but F has k={F.shape[1]} bases")
    if ordered and len(plan.perm) != F.shape[1]:
        raise ValueError("ordered coefficients need a plan that keeps every basis row (not mean_only)")
    return _HarmonicContraction.apply(F, weight, plan, ordered)


class ZernikeConv(nn.Module):
    r"""Zernike convolution on a surface with angular pooling (ZerNet, paper section 3.2).

    .. math::
        \mathbf{y}_p = \operatorname{pool}_{\varphi}\Big( \sum_{j=1}^{k} \sum_{c=1}^{C_{in}}
            F_p[j, c]\, \big(\mathrm{Rot}(\varphi)\, G\big)[j, c, :] \Big) + \mathbf{b},
        \qquad F_p = \big(\texttt{operator.apply}(\mathbf{x})\big)_p,

    where ``Rot(φ) G`` are the coefficients of the kernel turned by ``φ``
    (:func:`zernet.zernike.rotate_coefficients` along the basis axis) and ``pool`` is over
    ``φ_a = 2π a / s`` (``"max"``, ``"mean"``, ``"none"``) or over the whole circle (``"continuous"``).
    The rotations are computed through the harmonic form (module docstring): cost about twice one unrotated
    contraction whatever ``s`` is, exactly one for ``s = 1``.

    Args:
        in_channels: ``C_in``.
        out_channels: ``C_out``.
        n_max: highest radial degree of the Zernike basis (``k = (n_max + 1)(n_max + 2) / 2``; 5 -> 21).
        k: alternatively the number of bases (must be triangular); overrides ``n_max``.
        angular_resolution: ``s``, number of kernel rotations (ignored by ``"continuous"``).
        pooling: ``"max"`` (paper), ``"continuous"`` (max over the circle: exactly independent of each
            vertex's reference direction), ``"mean"``, or ``"none"``.
        bias: add a learnable bias ``(C_out,)``.

    Shapes:
        - input: ``x`` ``(N, C_in)``; ``operator`` anything with ``apply(x) -> (N, k, C_in)`` and ``.k``
          (a :class:`zernet.operators.PatchOperator`).
        - output: ``(N, C_out)``, or ``(N, s, C_out)`` with ``pooling="none"`` (angle ``a`` is the kernel
          turned by ``2π a / s``).

    Parameters: ``weight`` ``(k, C_in, C_out)`` (He-uniform with fan-in ``k C_in``), ``bias`` ``(C_out,)``
    (zeros).
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
    ):
        super().__init__()
        if k is not None:
            n_max = n_max_for(k)
        if pooling not in POOLING_MODES:
            raise ValueError(f"pooling must be one of {POOLING_MODES}, got {pooling!r}")
        if int(angular_resolution) < 1:
            raise ValueError(f"angular_resolution must be >= 1, got {angular_resolution}")
        self.in_channels = int(in_channels)
        self.out_channels = int(out_channels)
        self.n_max = int(n_max)
        self.k = num_bases(self.n_max)
        self.angular_resolution = int(angular_resolution)
        self.pooling = pooling
        self.weight = nn.Parameter(torch.empty(self.k, self.in_channels, self.out_channels))
        self.bias = nn.Parameter(torch.empty(self.out_channels)) if bias else None
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """He-uniform weights (fan-in ``k C_in``: the response is a dot product of that length), zero bias."""
        bound = math.sqrt(6.0 / (self.k * self.in_channels))
        nn.init.uniform_(self.weight, -bound, bound)
        if self.bias is not None:
            nn.init.zeros_(self.bias)

    def coefficients(self, x: Tensor, operator, basis_order: tuple | None = None) -> Tensor:
        """``F = operator.apply(x)``, checked: ``(N, k, C_in)``; basis rows in ``basis_order`` if given."""
        if x.dim() != 2 or x.shape[1] != self.in_channels:
            raise ValueError(f"{self.__class__.__name__}: x must be (N, {self.in_channels}), got {tuple(x.shape)}")
        if getattr(operator, "k", self.k) != self.k:
            raise ValueError(f"{self.__class__.__name__} has k={self.k} bases but the operator has k={operator.k}")
        F = operator.apply(x) if basis_order is None else operator.apply(x, basis_order=basis_order)
        if F.shape != (x.shape[0], self.k, self.in_channels):
            raise ValueError(
                f"operator.apply returned {tuple(F.shape)}, expected {(x.shape[0], self.k, self.in_channels)}"
            )
        return F

    def harmonics(self, x: Tensor, operator, angular_resolution: int | None = None) -> Tensor:
        """The response as trigonometric polynomials, ``(2 D + 1, N, C_out)`` (harmonic layout, no bias).

        ``angular_resolution=None`` gives the true polynomial (``D = n_max``); an integer ``s`` the folded
        one that agrees with it at ``2π a / s``.
        """
        F = self.coefficients(x, operator)
        return harmonic_contraction(F, self.weight, harmonic_plan(self.n_max, angular_resolution))

    @float32_forward
    def forward(self, x: Tensor, operator) -> Tensor:
        """``x`` ``(N, C_in)`` -> ``(N, C_out)`` (``(N, s, C_out)`` for ``pooling="none"``)."""
        # Ask the operator for the coefficients grouped by frequency when it can (saves a gather of F
        # forward and backward); any operator with a plain apply(x) works too.
        order = self.operator_basis_order() if getattr(operator, "accepts_basis_order", False) else None
        # (subclasses such as the paper's formulation override coefficients(x, operator) without an order)
        F = self.coefficients(x, operator) if order is None else self.coefficients(x, operator, basis_order=order)
        out = self._pooled_response(F, ordered=order is not None)
        if self.bias is not None:
            out = out + self.bias
        return out

    def operator_basis_order(self) -> tuple | None:
        """The basis order this layer asks of operators that accept one (``None``: the natural order).

        Data pipelines prepare the operator's matrices in this order ahead of the forward pass
        (:meth:`zernet.operators.PatchOperator.to`), so the reordering is not paid inside it.
        """
        plan = self._plan()
        if plan is None or plan.identity or len(plan.perm) != self.k:
            return None
        return tuple(int(i) for i in plan.perm)

    def _plan(self) -> HarmonicPlan | None:
        """The harmonic plan this layer's pooling needs (``None``: ``s = 1``, one plain contraction)."""
        if self.pooling == "continuous":
            return harmonic_plan(self.n_max, None)
        if self.angular_resolution == 1:
            return None
        return harmonic_plan(self.n_max, self.angular_resolution, mean_only=self.pooling == "mean")

    def _pooled_response(self, F: Tensor, ordered: bool = False) -> Tensor:
        """Pooled response without bias from ``F`` (basis rows in the plan's order if ``ordered``)."""
        N = F.shape[0]
        s = self.angular_resolution
        plan = self._plan()
        if plan is None:  # s = 1: one unrotated contraction
            out = F.reshape(N, -1) @ self.weight.reshape(-1, self.out_channels)
            return out.unsqueeze(1) if self.pooling == "none" else out
        H = harmonic_contraction(F, self.weight, plan, ordered)
        if self.pooling == "continuous":
            return continuous_max(H)
        if self.pooling == "mean":
            return H[0]
        if self.pooling == "max":
            return discrete_max(H, s)
        return evaluate_harmonics(H, equispaced_angles(s, H.dtype, H.device)).permute(1, 0, 2).contiguous()

    def __repr__(self) -> str:
        return (
            f"{self.__class__.__name__}({self.in_channels}, {self.out_channels}, n_max={self.n_max}, "
            f"k={self.k}, angular_resolution={self.angular_resolution}, pooling={self.pooling!r}, "
            f"bias={self.bias is not None})"
        )
