r"""Direction-preserving (gauge-equivariant) Zernike convolution (paper section 4.4, GUIDE section 2).

A *directional channel* at vertex ``q`` is a real function on the circle ``h_q(ψ)``, the angle ``ψ``
measured in ``q``'s tangent plane from ``q``'s reference direction ``e1_q`` towards ``e2_q``. It is
stored by its real Fourier coefficients up to order ``L``, in the layout ``[a_0, a_1, b_1, ..., a_L, b_L]``
along a *direction axis* of length ``2L + 1``:

.. math::
    h_q(ψ) = a_0 + \sum_{\ell=1}^{L} a_\ell \cos \ell ψ + b_\ell \sin \ell ψ .

This is the harmonic layout of :mod:`zernet.nn.pooling` (there along the first axis, here along axis 1),
whose :func:`~zernet.nn.pooling.continuous_max` and :func:`~zernet.nn.pooling.discrete_max` pool it.
:func:`fourier_to_samples` / :func:`samples_to_fourier` convert to and from ``s`` samples at
``ψ_a = 2π a / s``; :func:`rotate_fourier` gives the coefficients of ``h(ψ + δ)`` (the same convention as
:func:`zernet.zernike.rotate_coefficients`: each ``(a_ℓ, b_ℓ)`` turns by ``[[cos ℓδ, sin ℓδ], [-sin ℓδ,
cos ℓδ]]``).

**Transport.** ``γ_qp`` (:func:`zernet.polar.transport_angles`) is the angle, in ``p``'s frame, of ``q``'s
reference direction after the minimal rotation taking ``n_q`` onto ``n_p``: a direction at angle ``ψ`` in
``q``'s frame has angle ``ψ + γ_qp`` in ``p``'s. So in ``p``'s frame the channel of ``q`` reads
``h_q(ψ - γ_qp)``, complex coefficient ``ĥ_q(ℓ) e^{-iℓγ_qp}``; in the real layout

.. math::
    (a_\ell, b_\ell) \mapsto (a_\ell \cos \ell γ_{qp} - b_\ell \sin \ell γ_{qp},\;
                              a_\ell \sin \ell γ_{qp} + b_\ell \cos \ell γ_{qp}).

**Fit.** With ``A`` the scalar patch operator (``PatchOperator.matrix``, row ``p k + j``, column ``q``), the
Zernike coefficients of the transported channel in ``p``'s patch are, per order ``ℓ``,
``α_p(j, ℓ) = Σ_q A[(p, j), q] ĥ_q(ℓ) e^{-iℓγ_qp}``: with ``C_ℓ = A ⊙ cos ℓγ`` and ``S_ℓ = A ⊙ sin ℓγ``,
``α_a = C_ℓ a - S_ℓ b`` and ``α_b = S_ℓ a + C_ℓ b``. :class:`DirectionalOperator` holds, per order, ``C_ℓ`` and
``S_ℓ`` as one real sparse matrix, built once per surface and cached on the patch operator.

**Convolution.** The local field at ``p`` is ``F_p(r, θ; ψ) = Σ_{j, r} α_p[j, r] Z_j(r, θ) T_r(ψ)`` with
``T = (1, cos ψ, sin ψ, ..., cos Lψ, sin Lψ)``; a kernel is ``g(r, θ; ψ) = Σ_{j, r} G[j, r] Z_j T_r``.
The kernel turned to orientation ``φ`` in ``p``'s tangent plane is ``g_φ(r, θ; ψ) = g(r, θ - φ; ψ - φ)``
(the disk *and* its direction argument turn together) and the response is the inner product over the
disk and the mean over the circle,

.. math::
    o_p(φ) = \int_{D} \frac{1}{2π}\int_0^{2π} F_p\, g_φ \, dψ\, dA
           = \sum_{j, r, j', r'} α_p[j, r]\, w_r\, R(-φ)_{j j'}\, Q(-φ)_{r r'}\, G[j', r'],

``R`` the Zernike rotation (:func:`zernet.zernike.rotation_matrix`), ``Q`` its Fourier analogue
(:func:`fourier_rotation_matrix`) and ``w = (1, 1/2, ..., 1/2)`` the mean of ``T_r^2``. ``o_p`` is a
trigonometric polynomial in ``φ`` of degree ``<= n_max + L_in``; its Fourier coefficients up to
``L_out`` (or its values at ``s`` angles) are an exact, fixed linear function of ``G``. The layer
precomputes that coupling once (float64, by an exact DFT) and contracts in one dense matmul.

**Equivariance (sign conventions).** Turning ``p``'s frame by ``δ_p`` (``e1 ← cos δ e1 + sin δ e2``,
``e2 ← -sin δ e1 + cos δ e2``) changes its polar angles to ``θ - δ_p``, its operator rows to
``rotate_coefficients(·, δ_p)``, directional inputs to ``h_q(ψ + δ_q)`` (``rotate_fourier(·, δ_q)``) and
transport angles to ``γ_qp + δ_q - δ_p``. Then ``o_p(φ) → o_p(φ + δ_p)``: the output's Fourier
coefficients of order ``ℓ`` at ``p`` turn by ``ℓ δ_p`` (``rotate_fourier(·, δ_p)``), sampled outputs shift
cyclically by ``a`` when ``δ_p = 2π a / s``, and the maximum over the circle does not change at all.

Relation to :class:`zernet.nn.conv.ZernikeConv`, which evaluates ``Σ F · Rot(φ) G`` with
``Rot(φ) g = g(r, θ + φ)``: with ``L_in = 0`` and the kernel's ``ψ``-constant part equal to its weight,
``o_p(φ) = resp_p(-φ)``; both max-pool to the same value.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import scipy.sparse as sp
import torch
from torch import Tensor, nn

from zernet.patches import SparseApply, to_torch_csr
from zernet.polar import transport_angles
from zernet.zernike import n_max_for, num_bases, rotation_matrix

from .conv import float32_forward
from .models import register_model
from .pooling import continuous_max, discrete_max

__all__ = [
    "fourier_dim",
    "fourier_orders",
    "fourier_to_samples",
    "samples_to_fourier",
    "fourier_rotation_matrix",
    "rotate_fourier",
    "DirectionalOperator",
    "directional_operator",
    "coupling_tensor",
    "DirectionalZernikeConv",
    "DirectionalLifting",
    "DirectionalPooling",
    "DirectionalReLU",
    "DirectionalZerNet",
]


# --------------------------------------------------------------------------------------------------
# Functions on the circle: real Fourier layout [a_0, a_1, b_1, ..., a_L, b_L]
# --------------------------------------------------------------------------------------------------


def fourier_dim(order: int) -> int:
    """Length ``2 L + 1`` of the direction axis for Fourier order ``L``."""
    if order < 0:
        raise ValueError(f"Fourier order must be >= 0, got {order}")
    return 2 * int(order) + 1


def fourier_orders(order: int) -> np.ndarray:
    """Order ``ℓ`` of every entry of the layout ``[a_0, a_1, b_1, ...]``, shape ``(2L + 1,)``."""
    return np.concatenate([[0], np.repeat(np.arange(1, order + 1), 2)]).astype(np.int64)


def _trig_table(angles: np.ndarray, order: int) -> np.ndarray:
    """``T[a, r] = T_r(ψ_a)`` for ``T = (1, cos ψ, sin ψ, ..., cos Lψ, sin Lψ)``, shape ``(len, 2L + 1)``."""
    angles = np.asarray(angles, dtype=np.float64)
    table = np.empty((angles.shape[0], fourier_dim(order)), dtype=np.float64)
    table[:, 0] = 1.0
    for ell in range(1, order + 1):
        table[:, 2 * ell - 1] = np.cos(ell * angles)
        table[:, 2 * ell] = np.sin(ell * angles)
    return table


def _sample_angles(s: int) -> np.ndarray:
    if s < 1:
        raise ValueError(f"angular resolution s must be >= 1, got {s}")
    return np.arange(s, dtype=np.float64) * (2.0 * math.pi / s)


def _order_of(length: int) -> int:
    if length < 1 or length % 2 == 0:
        raise ValueError(f"a direction axis in Fourier layout has odd length 2L+1, got {length}")
    return (length - 1) // 2


def fourier_to_samples(coeffs: Tensor, s: int, dim: int = -2) -> Tensor:
    """Values ``h(ψ_a)`` at ``ψ_a = 2π a / s`` of circle functions given by Fourier coefficients.

    Args:
        coeffs: real Fourier coefficients, direction axis (length ``2L + 1``) at ``dim``,
            e.g. ``(N, 2L + 1, C)``.
        s: number of equally spaced angles.
        dim: direction axis.

    Returns:
        Same shape with the direction axis replaced by ``s`` samples, e.g. ``(N, s, C)``.
    """
    order = _order_of(coeffs.shape[dim])
    table = torch.as_tensor(_trig_table(_sample_angles(s), order), dtype=coeffs.dtype, device=coeffs.device)
    x = coeffs.movedim(dim, -1)
    return (x @ table.T).movedim(-1, dim)


def samples_to_fourier(samples: Tensor, order: int, dim: int = -2) -> Tensor:
    """Fourier coefficients up to order ``L`` of ``s`` equally spaced samples (the discrete Fourier transform).

    Exact inverse of :func:`fourier_to_samples` for functions of order ``<= L``; requires ``2L < s``.
    It commutes with cyclic shifts of the samples: shifting by ``a`` samples equals
    ``rotate_fourier(·, 2π a / s)``.

    Args:
        samples: values at ``ψ_a = 2π a / s`` along ``dim``, e.g. ``(N, s, C)``.
        order: ``L``.
        dim: direction axis.

    Returns:
        Same shape with ``s`` replaced by ``2L + 1``, e.g. ``(N, 2L + 1, C)``.
    """
    s = samples.shape[dim]
    if 2 * order >= s:
        raise ValueError(f"{s} samples determine Fourier orders < s/2 only; got order {order}")
    table = _trig_table(_sample_angles(s), order)  # (s, 2L+1)
    weights = np.full(fourier_dim(order), 2.0 / s)
    weights[0] = 1.0 / s
    dft = torch.as_tensor(table * weights, dtype=samples.dtype, device=samples.device)  # (s, 2L+1)
    x = samples.movedim(dim, -1)
    return (x @ dft).movedim(-1, dim)


def fourier_rotation_matrix(delta, order: int):
    """Matrix ``Q(δ)`` with ``rotate_fourier(c, δ) = Q(δ) @ c``; numpy (float64) or torch like ``delta``.

    Args:
        delta: angle(s), scalar or shape ``B``.
        order: ``L``.

    Returns:
        Shape ``B + (2L + 1, 2L + 1)``.
    """
    is_torch = isinstance(delta, torch.Tensor)
    lib = torch if is_torch else np
    if not is_torch:
        delta = np.asarray(delta, dtype=np.float64)
    d = fourier_dim(order)
    out = (
        torch.zeros(delta.shape + (d, d), dtype=delta.dtype, device=delta.device)
        if is_torch
        else np.zeros(delta.shape + (d, d))
    )
    out[..., 0, 0] = 1.0
    for ell in range(1, order + 1):
        c, s = lib.cos(ell * delta), lib.sin(ell * delta)
        i, k = 2 * ell - 1, 2 * ell
        out[..., i, i] = c
        out[..., i, k] = s
        out[..., k, i] = -s
        out[..., k, k] = c
    return out


def rotate_fourier(coeffs: Tensor, delta, dim: int = -2) -> Tensor:
    """Coefficients of ``h(ψ + δ)`` given those of ``h(ψ)``.

    Args:
        coeffs: Fourier coefficients with the direction axis (``2L + 1``) at ``dim``, e.g. ``(N, 2L + 1, C)``.
        delta: scalar angle, or a tensor broadcastable against ``coeffs`` with the direction axis removed
            (e.g. one angle per vertex, shape ``(N, 1)`` for ``(N, 2L + 1, C)``).
        dim: direction axis.

    Returns:
        Rotated coefficients, same shape.
    """
    order = _order_of(coeffs.shape[dim])
    x = coeffs.movedim(dim, -1)
    delta = torch.as_tensor(delta, dtype=x.dtype, device=x.device)
    q = fourier_rotation_matrix(delta, order)  # delta.shape + (d, d)
    return (q @ x.unsqueeze(-1)).squeeze(-1).movedim(-1, dim)


# --------------------------------------------------------------------------------------------------
# Transport angles and the transported patch operator
# --------------------------------------------------------------------------------------------------


class DirectionalOperator:
    r"""Transported Zernike fit of directional channels of Fourier order ``<= L``, for one surface.

    ``apply`` maps per-vertex channels ``h`` (``(N, 2L + 1, C)``, Fourier layout) to the Zernike
    coefficients of their transports into every vertex's patch, ``α[p, j, r, c]`` (module docstring).
    Order 0 needs no transport and goes through the scalar operator itself. For each order ``ℓ >= 1``
    one real sparse matrix ``phases[ℓ - 1]`` of shape ``(2 N k, N)`` interleaves ``C_ℓ = A ⊙ cos ℓγ``
    (row ``2 (p k + j)``) and ``S_ℓ = A ⊙ sin ℓγ`` (row ``2 (p k + j) + 1``); it is applied to
    ``[a_ℓ | b_ℓ]`` at once and ``α_a = C_ℓ a - S_ℓ b``, ``α_b = S_ℓ a + C_ℓ b``. Extra storage:
    ``2 L nnz(A)`` entries.

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

    @classmethod
    def from_patch_operator(cls, operator, order: int) -> DirectionalOperator:
        """Build from a :class:`~zernet.patches.PatchOperator` (its ``matrix``, ``k`` and ``frames``)."""
        fourier_dim(order)
        a = operator.matrix.tocsr()
        k = int(operator.k)
        n = int(a.shape[1])
        if order == 0:
            return cls(operator, [])
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
        return cls(operator, phases)

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


_CACHE_ATTRIBUTE = "_zernet_directional_operators"


def directional_operator(operator, order: int) -> DirectionalOperator:
    """The :class:`DirectionalOperator` of order ``L`` for a patch operator, built once and cached on it.

    ``operator`` may already be a :class:`DirectionalOperator` of that order (returned as is).
    """
    if isinstance(operator, DirectionalOperator):
        if operator.order != order:
            raise ValueError(f"directional operator has order {operator.order}, layer needs {order}")
        return operator
    cache = getattr(operator, _CACHE_ATTRIBUTE, None)
    if cache is None:
        cache = {}
        try:
            setattr(operator, _CACHE_ATTRIBUTE, cache)
        except AttributeError:  # an operator that refuses attributes: build every time
            pass
    if order not in cache:
        cache[order] = DirectionalOperator.from_patch_operator(operator, order)
    return cache[order]


# --------------------------------------------------------------------------------------------------
# Layers
# --------------------------------------------------------------------------------------------------


def _coupling(n_max: int, in_order: int, angles: np.ndarray) -> np.ndarray:
    """``K[b, x, y] = w_r R(-φ_b)[j, j'] Q(-φ_b)[r, r']`` for ``x = (j, r)``, ``y = (j', r')``."""
    rot = rotation_matrix(-angles, n_max)  # (B, k, k)
    q = fourier_rotation_matrix(-angles, in_order)  # (B, d, d)
    w = np.full(fourier_dim(in_order), 0.5)
    w[0] = 1.0
    k, d = rot.shape[-1], q.shape[-1]
    kern = np.einsum("bjJ,brR,r->bjrJR", rot, q, w)
    return kern.reshape(len(angles), k * d, k * d)


def coupling_tensor(n_max: int, in_order: int, out_order: int | None = None, samples: int | None = None) -> np.ndarray:
    """Fixed tensor ``E`` with ``o[t] = Σ_{x, y} α[x] G[y] E[x, y, t]`` (float64, exact).

    ``x = j (2L_in + 1) + r`` indexes the input field's coefficients, ``y`` the kernel's, and ``t`` either
    the output's real Fourier coefficients up to ``out_order`` or its values at ``samples`` angles
    ``2π a / s`` (give exactly one of the two).

    Returns:
        ``(k (2L_in + 1), k (2L_in + 1), T)`` with ``T = 2 out_order + 1`` or ``samples``.
    """
    if (out_order is None) == (samples is None):
        raise ValueError("give exactly one of out_order and samples")
    if samples is not None:
        return np.moveaxis(_coupling(n_max, in_order, _sample_angles(samples)), 0, -1)
    degree = max(n_max + in_order, out_order)
    grid = 2 * degree + 1  # exact DFT of a trigonometric polynomial of this degree
    values = _coupling(n_max, in_order, _sample_angles(grid))  # (grid, X, Y)
    table = _trig_table(_sample_angles(grid), out_order)  # (grid, T)
    weights = np.full(fourier_dim(out_order), 2.0 / grid)
    weights[0] = 1.0 / grid
    out = np.einsum("bxy,bt->xyt", values, table * weights)
    out[np.abs(out) < 1e-13] = 0.0
    return out


class DirectionalZernikeConv(nn.Module):
    r"""Direction-preserving Zernike convolution: directional channels in, directional channels out.

    For every vertex ``p``, output channel ``o`` and kernel orientation ``φ`` in ``p``'s tangent plane:

    .. math::
        y_p(φ)[o] = \sum_{c} \int_D \frac{1}{2π}\int_0^{2π}
                    F_p^{c}(r, θ; ψ)\, g^{c, o}(r, θ - φ; ψ - φ)\, dψ\, dA \;+\; b[o],

    where ``F_p^c`` is input channel ``c`` of every neighbour ``q`` transported into ``p``'s frame
    (``h_q(ψ - γ_qp)``) and fitted with Zernike polynomials (:class:`DirectionalOperator`), and
    ``g^{c,o}(r, θ; ψ) = Σ_{j, r} G[j, r, c, o] Z_j(r, θ) T_r(ψ)`` is a learned directional kernel
    (``T = (1, cos ψ, sin ψ, ..., cos L_in ψ, sin L_in ψ)``). ``y_p`` is a trigonometric polynomial in
    ``φ`` of degree ``<= n_max + L_in``, computed exactly (see the module docstring) as

    .. math::
        y_p[t, o] = \sum_{x, c} α_p[x, c]\, W[x, c, t, o] + b[o]\,[t = 0],\qquad
        W[x, c, t, o] = \sum_y E[x, y, t]\, G[y, c, o]

    with the fixed coupling ``E`` (:func:`coupling_tensor`), contracted block by block: output order ``μ``
    only involves the inputs ``(j, r)`` with ``|m_j| ± ℓ_r = ±μ`` (about a quarter of a dense contraction
    for the whole response). ``t`` runs over the output's real Fourier
    coefficients up to ``out_order`` (``output="fourier"``: the next layer's directional channel, exactly
    equivariant) or over ``s`` angles ``φ_a = 2π a / s`` (``output="samples"``: the exact response of
    ``s`` rotated kernels). The bias is direction-independent.

    Args:
        in_channels: ``C_in``.
        out_channels: ``C_out``.
        n_max: highest Zernike degree (``k = (n_max + 1)(n_max + 2) / 2`` must match the operator).
        order: Fourier order ``L_in`` of the input channels (0 lifts scalar features).
        out_order: Fourier order ``L_out`` of the output (``output="fourier"``); default ``order``.
            ``n_max + order`` keeps the whole response.
        angular_resolution: ``s``, number of output angles when ``output="samples"``.
        output: ``"fourier"`` or ``"samples"``.
        bias: learn a direction-independent bias.

    Shapes:
        - input: ``x`` ``(N, 2 L_in + 1, C_in)`` (or ``(N, C_in)`` when ``L_in = 0``); ``operator`` a
          :class:`~zernet.patches.PatchOperator` (its :class:`DirectionalOperator` is built once and
          cached on it) or a :class:`DirectionalOperator` of order ``L_in``.
        - output: ``(N, 2 L_out + 1, C_out)`` (``"fourier"``) or ``(N, s, C_out)`` (``"samples"``).
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        n_max: int = 5,
        order: int = 1,
        out_order: int | None = None,
        angular_resolution: int = 4,
        output: str = "fourier",
        bias: bool = True,
    ) -> None:
        super().__init__()
        if output not in ("fourier", "samples"):
            raise ValueError(f"output must be 'fourier' or 'samples', got {output!r}")
        if in_channels < 1 or out_channels < 1:
            raise ValueError(f"channel counts must be >= 1, got {in_channels} -> {out_channels}")
        self.in_channels = int(in_channels)
        self.out_channels = int(out_channels)
        self.n_max = int(n_max)
        self.k = num_bases(self.n_max)
        self.order = int(order)
        self.out_order = self.order if out_order is None else int(out_order)
        fourier_dim(self.order), fourier_dim(self.out_order)  # validate
        self.angular_resolution = int(angular_resolution)
        self.output = output
        d = fourier_dim(self.order)
        self.weight = nn.Parameter(torch.empty(self.k, d, self.in_channels, self.out_channels))
        self.bias = nn.Parameter(torch.empty(self.out_channels)) if bias else None
        if output == "fourier":
            coupling = coupling_tensor(self.n_max, self.order, out_order=self.out_order)
        else:
            coupling = coupling_tensor(self.n_max, self.order, samples=self.angular_resolution)
        # Block structure: output order μ (Fourier) only sees the inputs x = (j, r) whose orders m_j ± ℓ_r
        # reach ±μ, so the contraction is done per block (xs_b -> ts_b) instead of densely.
        x_dim, y_dim, t_dim = coupling.shape
        self.out_dim = t_dim
        if output == "fourier":
            ranges = [(0, 1)] + [(2 * mu - 1, 2 * mu + 1) for mu in range(1, self.out_order + 1)]
        else:
            ranges = [(0, t_dim)]
        blocks, block_x, entry_pos, entry_y, entry_val = [], [], [], [], []
        pos = x_count = 0
        for t0, t1 in ranges:
            sub = coupling[:, :, t0:t1]  # (X, Y, T_b)
            xs = np.flatnonzero(np.abs(sub).sum(axis=(1, 2)) > 0)
            ix, iy, it = np.nonzero(sub[xs])
            blocks.append((x_count, len(xs), t0, t1, pos))
            x_count += len(xs)
            block_x.append(xs)
            entry_pos.append(pos + ix * (t1 - t0) + it)
            entry_y.append(iy)
            entry_val.append(sub[xs][ix, iy, it])
            pos += len(xs) * (t1 - t0)
        self._blocks = blocks  # (x offset, n_b, t0, t1, W offset), python ints
        self._weight_rows = pos
        as_long = lambda parts: torch.from_numpy(np.concatenate(parts).astype(np.int64))  # noqa: E731
        self.register_buffer("block_x", as_long(block_x), persistent=False)
        self.register_buffer("entry_pos", as_long(entry_pos), persistent=False)
        self.register_buffer("entry_y", as_long(entry_y), persistent=False)
        self.register_buffer("entry_val", torch.from_numpy(np.concatenate(entry_val)), persistent=False)  # float64
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """He-uniform weights, zero bias.

        ``o(φ) = Σ α[j, r] w_r (R Q G)[j, r]`` with orthogonal ``R``, ``Q``: for inputs whose orders
        ``<= L`` carry equal power, ``Var o = Var G · k C_in E[h²] (1 + L) / (1 + 2L)``, so the bound is
        ``sqrt(6 (1 + 2L) / (k C_in (1 + L)))`` (:class:`~zernet.nn.conv.ZernikeConv`'s for ``L = 0``).
        """
        fan_in = self.k * self.in_channels * (1 + self.order) / (1 + 2 * self.order)
        bound = math.sqrt(6.0 / fan_in)
        nn.init.uniform_(self.weight, -bound, bound)
        if self.bias is not None:
            nn.init.zeros_(self.bias)

    def block_weights(self) -> list[Tensor]:
        """``W`` per output block ``b``: ``(n_b C_in, T_b C_out)``, rows ``(x ∈ xs_b, c)``, columns ``(t ∈ ts_b, o)``.

        ``W[x, c, t, o] = Σ_y E[x, y, t] G[y, c, o]`` over the few non-zero couplings ``E`` only.
        """
        c_in, c_out = self.in_channels, self.out_channels
        g = self.weight.reshape(-1, c_in * c_out)
        contribution = self.entry_val.to(g.dtype)[:, None] * g.index_select(0, self.entry_y)
        w_all = g.new_zeros(self._weight_rows, c_in * c_out).index_add(0, self.entry_pos, contribution)
        out = []
        for _, nx, t0, t1, p0 in self._blocks:
            tb = t1 - t0
            w = w_all[p0 : p0 + nx * tb].view(nx, tb, c_in, c_out).permute(0, 2, 1, 3)
            out.append(w.reshape(nx * c_in, tb * c_out))
        return out

    def fit(self, x: Tensor, operator) -> Tensor:
        """Transported Zernike coefficients ``α``: ``(N, 2 L_in + 1, C_in)`` -> ``(N, k, 2 L_in + 1, C_in)``."""
        if x.dim() == 2 and self.order == 0:
            x = x.unsqueeze(1)
        d = fourier_dim(self.order)
        if x.dim() != 3 or x.shape[1] != d or x.shape[2] != self.in_channels:
            raise ValueError(
                f"expected input (N, {d}, {self.in_channels}) (Fourier order {self.order}), got {tuple(x.shape)}"
            )
        if operator.k != self.k:
            raise ValueError(f"layer has k={self.k} Zernike bases (n_max={self.n_max}) but the operator has k={operator.k}")
        if self.order == 0 and not isinstance(operator, DirectionalOperator):
            return operator.apply(x[:, 0]).unsqueeze(2)  # no transport for scalars: the plain operator
        return directional_operator(operator, self.order).apply(x)

    @float32_forward
    def forward(self, x: Tensor, operator) -> Tensor:
        """``x`` ``(N, 2 L_in + 1, C_in)`` -> ``(N, 2 L_out + 1, C_out)`` or ``(N, s, C_out)``."""
        coeffs = self.fit(x, operator)
        n = coeffs.shape[0]
        alpha = coeffs.reshape(n, -1, self.in_channels)  # (N, X, C_in), x = j (2 L_in + 1) + r
        parts = []
        for (x0, nx, t0, t1, _), w in zip(self._blocks, self.block_weights()):
            if nx == 0:  # orders beyond n_max + L_in: identically zero
                parts.append(alpha.new_zeros(n, t1 - t0, self.out_channels))
                continue
            xs = self.block_x[x0 : x0 + nx]
            a = alpha if nx == alpha.shape[1] else alpha.index_select(1, xs)
            parts.append((a.reshape(n, nx * self.in_channels) @ w).view(n, t1 - t0, self.out_channels))
        out = torch.cat(parts, dim=1) if len(parts) > 1 else parts[0]
        if self.bias is not None:
            if self.output == "fourier":
                out = torch.cat([out[:, :1] + self.bias, out[:, 1:]], dim=1)
            else:
                out = out + self.bias
        return out

    def extra_repr(self) -> str:
        target = f"out_order={self.out_order}" if self.output == "fourier" else f"samples={self.angular_resolution}"
        return (
            f"{self.in_channels}, {self.out_channels}, n_max={self.n_max}, order={self.order}, {target}, "
            f"bias={self.bias is not None}"
        )


class DirectionalLifting(DirectionalZernikeConv):
    r"""Lifting layer: scalar features in, directional channels out (``DirectionalZernikeConv`` with ``L_in = 0``).

    .. math::
        y_p(φ)[o] = \sum_{c, j} F_p[j, c]\, (R(-φ) G)[j, c, o] + b[o]
                  = \sum_c \int_D f_p^c(r, θ)\, g^{c, o}(r, θ - φ)\, dA + b[o]

    kept as Fourier coefficients up to ``out_order`` (or ``s`` samples).

    Args:
        in_channels, out_channels, n_max, angular_resolution, output, bias: as :class:`DirectionalZernikeConv`.
        out_order: ``L_out`` (default 1; ``n_max`` keeps the whole response).

    Shapes:
        - input: ``x`` ``(N, C_in)``; ``operator`` a :class:`~zernet.patches.PatchOperator`.
        - output: ``(N, 2 L_out + 1, C_out)`` or ``(N, s, C_out)``.
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        n_max: int = 5,
        out_order: int = 1,
        angular_resolution: int = 4,
        output: str = "fourier",
        bias: bool = True,
    ) -> None:
        super().__init__(
            in_channels,
            out_channels,
            n_max=n_max,
            order=0,
            out_order=out_order,
            angular_resolution=angular_resolution,
            output=output,
            bias=bias,
        )


class DirectionalPooling(nn.Module):
    r"""Pooling over the direction axis: directional channels -> scalars.

    - ``"continuous"``: ``max_ψ h(ψ)`` over the whole circle (:func:`zernet.nn.pooling.continuous_max`); independent of the
      reference direction for any rotation.
    - ``"discrete"``: ``max_a h(2π a / s)`` (:func:`zernet.nn.pooling.discrete_max`); independent of rotations by multiples of ``2π / s``.
    - ``"mean"``: ``a_0``, the mean over the circle.

    Args:
        mode: ``"continuous"``, ``"discrete"`` or ``"mean"``.
        angular_resolution: ``s`` for ``"discrete"``.
        newton_steps: refinement steps of the continuous max (passed to
            :func:`~zernet.nn.pooling.continuous_max`).

    Shapes:
        - input: ``(N, 2L + 1, C)`` Fourier coefficients.
        - output: ``(N, C)``.
    """

    def __init__(self, mode: str = "continuous", angular_resolution: int = 4, newton_steps: int = 3) -> None:
        super().__init__()
        if mode not in ("continuous", "discrete", "mean"):
            raise ValueError(f"pooling mode must be 'continuous', 'discrete' or 'mean', got {mode!r}")
        self.mode = mode
        self.angular_resolution = int(angular_resolution)
        self.newton_steps = int(newton_steps)

    def forward(self, x: Tensor) -> Tensor:
        """``(N, 2L + 1, C)`` -> ``(N, C)``."""
        if self.mode == "mean":
            return x[:, 0]
        if self.mode == "discrete":
            return discrete_max(x.transpose(0, 1), self.angular_resolution)
        return continuous_max(x.transpose(0, 1), newton_steps=self.newton_steps)

    def extra_repr(self) -> str:
        return f"mode={self.mode!r}" + (f", s={self.angular_resolution}" if self.mode == "discrete" else "")


class DirectionalReLU(nn.Module):
    r"""Nonlinearity for directional channels.

    - ``"regular"``: ReLU of the values at ``s`` angles, back to Fourier order ``L`` by the discrete
      Fourier transform: ``samples_to_fourier(relu(fourier_to_samples(h, s)), L)``. Equivariant exactly
      for rotations by multiples of ``2π / s`` (the paper's ``s``-angle activations).
    - ``"norm"``: ReLU of ``a_0``; every order ``ℓ >= 1`` pair scaled by ``relu(|(a_ℓ, b_ℓ)| + β) /
      |(a_ℓ, b_ℓ)|`` with a learned ``β[ℓ, c]`` (zero at initialisation). Equivariant exactly for every
      rotation.

    Args:
        channels: ``C``.
        order: ``L``.
        mode: ``"regular"`` or ``"norm"``.
        angular_resolution: ``s`` for ``"regular"`` (``> 2L``).

    Shapes:
        - input / output: ``(N, 2L + 1, C)``.
    """

    def __init__(self, channels: int, order: int, mode: str = "regular", angular_resolution: int = 4) -> None:
        super().__init__()
        if mode not in ("regular", "norm"):
            raise ValueError(f"nonlinearity must be 'regular' or 'norm', got {mode!r}")
        if mode == "regular" and 2 * order >= angular_resolution:
            raise ValueError(f"regular nonlinearity needs s > 2L, got s={angular_resolution}, L={order}")
        self.channels = int(channels)
        self.order = int(order)
        self.mode = mode
        self.angular_resolution = int(angular_resolution)
        self.norm_bias = nn.Parameter(torch.zeros(self.order, self.channels)) if mode == "norm" and order > 0 else None

    def reset_parameters(self) -> None:
        if self.norm_bias is not None:
            nn.init.zeros_(self.norm_bias)

    def forward(self, x: Tensor) -> Tensor:
        """``(N, 2L + 1, C)`` -> ``(N, 2L + 1, C)``."""
        if self.mode == "regular":
            return samples_to_fourier(torch.relu(fourier_to_samples(x, self.angular_resolution, dim=1)), self.order, dim=1)
        if self.order == 0:
            return torch.relu(x)
        n = x.shape[0]
        pairs = x[:, 1:].view(n, self.order, 2, self.channels)
        eps = torch.finfo(x.dtype).eps
        norm = torch.sqrt((pairs**2).sum(2, keepdim=True) + eps)
        scale = torch.relu(norm + self.norm_bias[:, None, :]) / norm
        return torch.cat([torch.relu(x[:, :1]), (pairs * scale).reshape(n, 2 * self.order, self.channels)], dim=1)

    def extra_repr(self) -> str:
        return f"{self.channels}, order={self.order}, mode={self.mode!r}" + (
            f", s={self.angular_resolution}" if self.mode == "regular" else ""
        )


# --------------------------------------------------------------------------------------------------
# Model
# --------------------------------------------------------------------------------------------------


@register_model("zernet-directional")
class DirectionalZerNet(nn.Module):
    r"""ZerNet with direction-preserving convolutions (paper section 4.4).

    ``DirectionalLifting(w_0) -> act -> (DirectionalZernikeConv(w_i), act)_i -> DirectionalZernikeConv(w_last,
    whole response) -> DirectionalPooling -> ReLU -> Lin(widths[-1]), ReLU -> Dropout -> Lin(out_channels)``

    Between convolution blocks every feature keeps its direction axis as Fourier coefficients of order
    ``L`` (default ``(s - 1) // 2``: ``L = 1`` at the paper's ``s = 4``); ``act`` is
    :class:`DirectionalReLU`. The last convolution keeps its whole response (order ``n_max + L``), which
    ``pooling`` reduces to scalars. At the default widths this is the paper's
    ``Conv64 -> Conv128 -> Conv256 -> Lin512 -> Lin(C)``.

    Args:
        in_channels: ``C_in``.
        out_channels: ``C_out``.
        widths: convolution widths followed by the hidden linear width.
        k: Zernike bases per patch (21 in the paper).
        angular_resolution: ``s`` (4 in the paper).
        order: ``L`` of the directional features; default ``(s - 1) // 2``.
        pooling: ``"continuous"`` (default), ``"discrete"`` or ``"mean"`` at the end.
        nonlinearity: ``"regular"`` (ReLU at the ``s`` angles, default) or ``"norm"``.
        dropout: dropout probability before the output layer.

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
        angular_resolution: int = 4,
        order: int | None = None,
        pooling: str = "continuous",
        nonlinearity: str = "regular",
        dropout: float = 0.25,
    ) -> None:
        super().__init__()
        widths = tuple(int(w) for w in widths)
        if len(widths) < 2 or min(widths) < 1:
            raise ValueError(
                f"widths must list at least one convolution width and the hidden linear width, all >= 1, "
                f"e.g. (64, 128, 256, 512); got {widths}"
            )
        self.in_channels = int(in_channels)
        self.out_channels = int(out_channels)
        self.widths = widths
        n_max = n_max_for(int(k))
        s = int(angular_resolution)
        order = (s - 1) // 2 if order is None else int(order)
        self.order = order
        conv_widths = widths[:-1]
        self.convs = nn.ModuleList()
        self.acts = nn.ModuleList()
        channels, in_order = self.in_channels, 0
        for i, width in enumerate(conv_widths):
            last = i == len(conv_widths) - 1
            self.convs.append(
                DirectionalZernikeConv(
                    channels, width, n_max=n_max, order=in_order, out_order=n_max + in_order if last else order
                )
            )
            if not last:
                self.acts.append(DirectionalReLU(width, order, mode=nonlinearity, angular_resolution=s))
            channels, in_order = width, order
        self.pool = DirectionalPooling(pooling, angular_resolution=s)
        self.hidden = nn.Linear(channels, widths[-1])
        self.dropout = nn.Dropout(dropout)
        self.output = nn.Linear(widths[-1], out_channels)

    def forward(self, x: Tensor, geometry) -> Tensor:
        """``x`` ``(N, C_in)``, ``geometry.operators[0]`` -> ``(N, C_out)``."""
        operator = geometry.operators[0]
        h = x
        for i, conv in enumerate(self.convs):
            h = conv(h, operator)
            if i < len(self.acts):
                h = self.acts[i](h)
        h = torch.relu(self.pool(h))
        h = torch.relu(self.hidden(h))
        return self.output(self.dropout(h))
