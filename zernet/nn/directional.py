r"""Direction-preserving (gauge-equivariant) Zernike convolution layers (paper section 4.4).

A *directional channel* at vertex ``q`` is a real function on the circle ``h_q(ψ)``, the angle ``ψ``
measured in ``q``'s tangent plane from ``q``'s reference direction ``e1_q`` towards ``e2_q``, stored by its
real Fourier coefficients up to order ``L`` along axis 1 (layout and helpers in :mod:`zernet.fourier`).
The channels of every neighbour, transported into ``p``'s frame and fitted with Zernike polynomials, are
``α_p[j, r]`` = :meth:`zernet.operators.DirectionalOperator.apply` (transport and fit explained in
:mod:`zernet.operators.directional`); that operator is built once per surface when the data are prepared
and handed to the layers, which never build it themselves.

**Convolution.** The local field at ``p`` is ``F_p(r, θ; ψ) = Σ_{j, r} α_p[j, r] Z_j(r, θ) T_r(ψ)`` with
``T = (1, cos ψ, sin ψ, ..., cos Lψ, sin Lψ)``; a kernel is ``g(r, θ; ψ) = Σ_{j, r} G[j, r] Z_j T_r``.
The kernel turned to orientation ``φ`` in ``p``'s tangent plane is ``g_φ(r, θ; ψ) = g(r, θ - φ; ψ - φ)``
(the disk *and* its direction argument turn together) and the response is the inner product over the
disk and the mean over the circle,

.. math::
    o_p(φ) = \int_{D} \frac{1}{2π}\int_0^{2π} F_p\, g_φ \, dψ\, dA
           = \sum_{j, r, j', r'} α_p[j, r]\, w_r\, R(-φ)_{j j'}\, Q(-φ)_{r r'}\, G[j', r'],

``R`` the Zernike rotation (:func:`zernet.zernike.rotation_matrix`), ``Q`` its Fourier analogue
(:func:`zernet.fourier.fourier_rotation_matrix`) and ``w = (1, 1/2, ..., 1/2)`` the mean of ``T_r^2``. ``o_p`` is a
trigonometric polynomial in ``φ`` of degree ``<= n_max + L_in``; its Fourier coefficients up to
``L_out`` (or its values at ``s`` angles) are an exact, fixed linear function of ``G``. The layer
precomputes that coupling once (float64, by an exact DFT; :mod:`zernet.nn.directional_plan`), asks the
directional operator for only the input harmonics the output needs, and contracts block by block.

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

import torch
from torch import Tensor, nn

from zernet.fourier import fourier_dim, fourier_to_samples, samples_to_fourier
from zernet.operators.directional import DirectionalOperator
from zernet.zernike import num_bases

from .conv import float32_forward
from .directional_plan import coupling_tensor, directional_plan, harmonic_weights, plan_contraction
from .pooling import continuous_max, discrete_max

__all__ = [
    "coupling_tensor",
    "DirectionalZernikeConv",
    "DirectionalLifting",
    "DirectionalPooling",
    "DirectionalReLU",
    "DirectionalLayerNorm",
]


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

    with the fixed coupling ``E`` (:func:`coupling_tensor`), contracted block by block
    (:mod:`zernet.nn.directional_plan`): output order ``μ`` only involves the inputs ``(j, r)`` with
    ``|m_j| ± ℓ_r = ±μ``, and the operator computes only the inputs some output needs. ``t`` runs over the output's real Fourier
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
          :class:`~zernet.operators.DirectionalOperator` of order ``L_in``
          (:func:`~zernet.operators.build_directional_operator`), or for ``L_in = 0`` also the scalar
          :class:`~zernet.operators.PatchOperator`.
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
            self.plan = directional_plan(self.n_max, self.order, out_order=self.out_order)
        else:
            self.plan = directional_plan(self.n_max, self.order, samples=self.angular_resolution)
        self.out_dim = self.plan.out_dim
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
        """``W`` per output block of :attr:`plan` (:func:`~zernet.nn.directional_plan.harmonic_weights`)."""
        return harmonic_weights(self.weight, self.plan)

    def fit(self, x: Tensor, operator) -> Tensor:
        """Transported Zernike coefficients ``α``: ``(N, 2 L_in + 1, C_in)`` -> ``(N, k, 2 L_in + 1, C_in)``."""
        if x.dim() == 2 and self.order == 0:
            x = x.unsqueeze(1)
        self.fit_check(x, operator)
        if self.order == 0 and not isinstance(operator, DirectionalOperator):
            return operator.apply(x[:, 0]).unsqueeze(2)  # no transport for scalars: the plain operator
        return operator.apply(x)

    def fit_check(self, x: Tensor, operator) -> None:
        """``ValueError`` unless ``x`` and ``operator`` fit this layer (naming the fix)."""
        d = fourier_dim(self.order)
        if x.dim() != 3 or x.shape[1] != d or x.shape[2] != self.in_channels:
            raise ValueError(
                f"expected input (N, {d}, {self.in_channels}) (Fourier order {self.order}), got {tuple(x.shape)}"
            )
        if operator.k != self.k:
            raise ValueError(
                f"layer has k={self.k} Zernike bases (n_max={self.n_max}) but the operator has k={operator.k}"
            )
        if self.order == 0 and not isinstance(operator, DirectionalOperator):
            return
        if not isinstance(operator, DirectionalOperator) or operator.order != self.order:
            have = f"order {operator.order}" if isinstance(operator, DirectionalOperator) else type(operator).__name__
            raise ValueError(
                f"{type(self).__name__} with input order {self.order} needs a DirectionalOperator of order "
                f"{self.order}, got {have}: build it once per surface with "
                f"zernet.operators.build_directional_operator(operator, {self.order})"
            )

    def harmonics(self, x: Tensor, operator) -> Tensor:
        """The input harmonics the output needs, ``(N, len(plan.inputs), C_in)`` in plan order."""
        if x.dim() == 2 and self.order == 0:
            x = x.unsqueeze(1)
        if not isinstance(operator, DirectionalOperator) or self.order == 0:
            coeffs = self.fit(x, operator)  # scalar inputs: the plain operator, then the plan's rows
            flat = coeffs.reshape(coeffs.shape[0], -1, self.in_channels)
            inputs = self.plan.inputs
            if inputs == tuple(range(flat.shape[1])):
                return flat
            return flat.index_select(1, torch.as_tensor(inputs, device=flat.device))
        self.fit_check(x, operator)
        return operator.apply_harmonic(x, self.plan.inputs)

    @float32_forward
    def forward(self, x: Tensor, operator) -> Tensor:
        """``x`` ``(N, 2 L_in + 1, C_in)`` -> ``(N, 2 L_out + 1, C_out)`` or ``(N, s, C_out)``."""
        out = plan_contraction(self.harmonics(x, operator), self.block_weights(), self.plan)
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
        - input: ``x`` ``(N, C_in)``; ``operator`` a :class:`~zernet.operators.PatchOperator`.
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
            return samples_to_fourier(
                torch.relu(fourier_to_samples(x, self.angular_resolution, dim=1)), self.order, dim=1
            )
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


class DirectionalLayerNorm(nn.Module):
    r"""Layer normalisation of directional channels, equivariant for every rotation.

    Each vertex's ``C`` channels are functions on the circle; they are normalised together, as a layer norm
    of their values over all channels and directions would:

    .. math::
        μ = \frac{1}{C}\sum_c a_{0,c}, \qquad
        σ^2 = \frac{1}{C}\sum_c \frac{1}{2π}\int_0^{2π} (h_c(ψ) - μ)^2 dψ
            = \frac{1}{C}\sum_c \Big[(a_{0,c} - μ)^2 + \tfrac12 \sum_{ℓ \ge 1} a_{ℓ,c}^2 + b_{ℓ,c}^2\Big],

    ``h_c ← γ_c (h_c - μ) / \sqrt{σ^2 + ε} + β_c``. ``μ`` and ``β`` touch only ``a_0``; ``σ`` and the per-channel
    gain ``γ`` are the same for every order, and a rotation keeps every ``|(a_ℓ, b_ℓ)|``: so the layer commutes
    with :func:`zernet.fourier.rotate_fourier` for any angle, whatever the order ``L`` of its input.

    Args:
        channels: ``C``.
        eps: ``ε``.

    Shapes:
        - input / output: ``(N, 2L + 1, C)``.
    """

    def __init__(self, channels: int, eps: float = 1e-5) -> None:
        super().__init__()
        self.channels, self.eps = int(channels), float(eps)
        self.weight = nn.Parameter(torch.ones(self.channels))
        self.bias = nn.Parameter(torch.zeros(self.channels))

    def reset_parameters(self) -> None:
        nn.init.ones_(self.weight)
        nn.init.zeros_(self.bias)

    def forward(self, x: Tensor) -> Tensor:
        """``(N, 2L + 1, C)`` -> ``(N, 2L + 1, C)``."""
        if x.dim() != 3 or x.shape[2] != self.channels or x.shape[1] % 2 != 1:
            raise ValueError(f"DirectionalLayerNorm expects (N, 2L + 1, {self.channels}), got {tuple(x.shape)}")
        mean = x[:, :1].mean(dim=2, keepdim=True)
        centred = torch.cat([x[:, :1] - mean, x[:, 1:]], dim=1)
        # mean of cos² and sin² over the circle is 1/2: the orders >= 1 weigh half of a_0
        squares = centred.square()
        power = squares[:, 0] + 0.5 * squares[:, 1:].sum(dim=1)
        scale = torch.rsqrt(power.mean(dim=1) + self.eps)[:, None, None]
        y = centred * scale * self.weight
        return torch.cat([y[:, :1] + self.bias, y[:, 1:]], dim=1)

    def extra_repr(self) -> str:
        return f"{self.channels}, eps={self.eps}"
