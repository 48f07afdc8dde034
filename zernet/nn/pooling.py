r"""Angular pooling of Zernike convolution responses, and the harmonic-form helpers.

The response of a Zernike convolution at a vertex, as a function of the kernel rotation :math:`\varphi`, is a
trigonometric polynomial of degree :math:`D \le n_{max}` (:mod:`zernet.nn.conv` derives it):

.. math::
    \mathrm{resp}(\varphi) = A_0 + \sum_{m=1}^{D} \big(A_m \cos m\varphi + B_m \sin m\varphi\big).

**Harmonic layout** (used by every function here, by :class:`~zernet.nn.conv.ZernikeConv` and by
:mod:`zernet.nn.directional`): a tensor ``H`` of shape ``(2 D + 1, *rest)`` whose slabs are
``H[0] = A_0``, ``H[2 m - 1] = A_m``, ``H[2 m] = B_m``; ``rest`` is typically ``(N, C)``. The matching
trigonometric basis is :func:`trig_basis`: ``[1, cos φ, sin φ, cos 2φ, sin 2φ, ...]``, so that
``resp(φ) = trig_basis(φ, D) @ H`` (contracting the first axis of ``H``).

Pooling modes:

* ``"max"``: the paper's discrete max over ``s`` equispaced angles ``φ_a = 2π a / s``
  (:func:`discrete_max`); invariant exactly to reference-direction changes by multiples of ``2π / s``.
* ``"continuous"``: the max over the whole circle (:func:`continuous_max`: closed-form for degree 1, else a
  dense grid, then Newton steps on ``resp'``); independent of every vertex's reference direction up to
  float rounding.
* ``"mean"``: the mean over the ``s`` angles, which is ``A_0`` (:func:`harmonic_mean`).
* ``"none"``: the ``s`` samples themselves (:func:`evaluate_harmonics`).

:func:`angular_pool` pools responses that are already sampled at ``s`` angles, shape ``(N, s, C)``.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = [
    "POOLING_MODES",
    "harmonic_degree",
    "trig_basis",
    "equispaced_angles",
    "evaluate_harmonics",
    "harmonic_mean",
    "discrete_max",
    "continuous_max",
    "angular_pool",
]

POOLING_MODES = ("max", "continuous", "mean", "none")

# Columns of H processed at once when sampling it at many angles: bounds the transient (s, chunk) buffer.
_CHUNK_ELEMENTS = 1 << 21
# Samples per chunk in the discrete max (a 4 MB block in float32): large enough to amortise the per-chunk
# calls, small enough to stay in cache between the product and the two reductions.
_POOL_CHUNK_ELEMENTS = 1 << 20


def harmonic_degree(harmonics: Tensor) -> int:
    """Degree ``D`` of harmonics of shape ``(2 D + 1, ...)``."""
    t = harmonics.shape[0]
    if t % 2 != 1:
        raise ValueError(f"harmonics must have an odd leading size 2*D+1, got shape {tuple(harmonics.shape)}")
    return (t - 1) // 2


def trig_basis(angles: Tensor, degree: int) -> Tensor:
    """Trigonometric basis ``[1, cos φ, sin φ, ..., cos Dφ, sin Dφ]``.

    Args:
        angles: angles ``φ``, any shape ``S``.
        degree: ``D``.

    Returns:
        Shape ``S + (2 D + 1,)``, dtype and device of ``angles``.
    """
    m = torch.arange(1, degree + 1, dtype=angles.dtype, device=angles.device)
    ma = angles[..., None] * m
    out = torch.empty(angles.shape + (2 * degree + 1,), dtype=angles.dtype, device=angles.device)
    out[..., 0] = 1.0
    out[..., 1::2] = torch.cos(ma)
    out[..., 2::2] = torch.sin(ma)
    return out


def equispaced_angles(s: int, dtype=torch.float32, device=None) -> Tensor:
    """The ``s`` kernel rotations ``φ_a = 2π a / s``, ``a = 0..s-1`` (computed in float64, then cast)."""
    return (torch.arange(s, dtype=torch.float64) * (2.0 * math.pi / s)).to(dtype=dtype, device=device)


def evaluate_harmonics(harmonics: Tensor, angles: Tensor) -> Tensor:
    """Sample the trigonometric polynomials at given angles (differentiable).

    Args:
        harmonics: ``H`` of shape ``(2 D + 1, *rest)`` in the harmonic layout.
        angles: ``(s,)`` angles.

    Returns:
        ``(s, *rest)``: ``out[a] = resp(angles[a])``.
    """
    D = harmonic_degree(harmonics)
    T = trig_basis(angles.to(harmonics.dtype), D)
    rest = harmonics.shape[1:]
    if D == 0:
        return harmonics.expand((angles.shape[0],) + tuple(rest))
    return (T @ harmonics.reshape(2 * D + 1, -1)).view((angles.shape[0],) + tuple(rest))


def harmonic_mean(harmonics: Tensor) -> Tensor:
    """Mean over a full period, which equals the mean over any ``s > D`` equispaced angles: ``H[0]``.

    The aliased ("folded") harmonics that :class:`~zernet.nn.conv.ZernikeConv` computes for ``s`` angles
    have degree ``<= s / 2`` with ``B_{s/2} = 0``, so their ``H[0]`` is the mean over the ``s`` angles too.
    """
    harmonic_degree(harmonics)
    return harmonics[0]


class _DiscreteMax(torch.autograd.Function):
    """max over the rows of ``T @ H`` with a sparse backward (only the winning angle receives gradient)."""

    @staticmethod
    def forward(ctx, H2: Tensor, T: Tensor) -> Tensor:  # H2 (t, M), T (s, t)
        s, M = T.shape[0], H2.shape[1]
        small = torch.uint8 if s <= 256 else torch.int16 if s <= 32768 else torch.int64
        values = torch.empty(M, dtype=H2.dtype, device=H2.device)
        index = torch.empty(M, dtype=small, device=H2.device)
        angle = torch.arange(s, dtype=small, device=H2.device)[:, None]
        # Cache-sized column chunks; the winning angle as the largest angle index equal to the maximum
        # (two vectorised reductions: torch.max with indices over the angle axis is several times slower).
        chunk = max(1, _POOL_CHUNK_ELEMENTS // s)
        samples = torch.empty(s, min(chunk, M), dtype=H2.dtype, device=H2.device)
        for start in range(0, M, chunk):
            stop = min(M, start + chunk)
            block = torch.mm(T, H2[:, start:stop], out=samples[:, : stop - start])
            best = torch.amax(block, dim=0, out=values[start:stop])
            torch.amax(torch.eq(block, best) * angle, dim=0, out=index[start:stop])
        ctx.save_for_backward(index, T)
        return values

    @staticmethod
    def backward(ctx, grad: Tensor):
        index, T = ctx.saved_tensors
        # (t, M): the trig basis at each element's winning angle (one gather with a broadcast index),
        # scaled in place by the incoming gradient.
        t, M = T.shape[1], index.shape[0]
        out = torch.gather(T.t().contiguous(), 1, index.long().expand(t, M))
        return out.mul_(grad), None


class _ValueAtAngle(torch.autograd.Function):
    """``resp(φ)`` per element for per-element angles ``φ`` treated as constants."""

    @staticmethod
    def forward(ctx, H2: Tensor, phi: Tensor) -> Tensor:  # H2 (t, M), phi (M,)
        D = (H2.shape[0] - 1) // 2
        ctx.save_for_backward(phi)
        ctx.degree = D
        value, _, _ = _poly_and_derivatives(H2, phi, D, derivatives=False)
        return value

    @staticmethod
    def backward(ctx, grad: Tensor):
        (phi,) = ctx.saved_tensors
        D = ctx.degree
        out = torch.empty((2 * D + 1,) + tuple(grad.shape), dtype=grad.dtype, device=grad.device)
        out[0] = grad
        c1, s1 = torch.cos(phi), torch.sin(phi)
        c, s = c1, s1
        for m in range(1, D + 1):
            out[2 * m - 1] = c * grad
            out[2 * m] = s * grad
            c, s = c * c1 - s * s1, s * c1 + c * s1
        return out, None


def _poly_and_derivatives(H2: Tensor, phi: Tensor, D: int, derivatives: bool = True):
    """``resp(φ)``, ``resp'(φ)``, ``resp''(φ)`` per column of ``H2`` (t, M) at angles ``phi`` (M,)."""
    value = H2[0].expand(phi.shape).clone()
    d1 = torch.zeros_like(value) if derivatives else None
    d2 = torch.zeros_like(value) if derivatives else None
    if D == 0:
        return value, d1, d2
    c1, s1 = torch.cos(phi), torch.sin(phi)
    c, s = c1, s1
    for m in range(1, D + 1):
        A, B = H2[2 * m - 1], H2[2 * m]
        even = A * c + B * s
        value += even
        if derivatives:
            d1 += m * (B * c - A * s)
            d2 -= (m * m) * even
        if m < D:
            c, s = c * c1 - s * s1, s * c1 + c * s1  # angle addition: cos/sin of (m + 1) φ
    return value, d1, d2


def discrete_max(harmonics: Tensor, s: int) -> Tensor:
    """The paper's angular max pooling over ``s`` equispaced kernel rotations ``φ_a = 2π a / s``.

    Args:
        harmonics: ``(2 D + 1, *rest)`` harmonic layout.
        s: angular resolution.

    Returns:
        ``rest``-shaped maxima. Gradient flows to the harmonics through the winning angle only; the
        ``(s, *rest)`` samples are never kept (built in column chunks).
    """
    D = harmonic_degree(harmonics)
    rest = harmonics.shape[1:]
    if D == 0 or s == 1:
        T = trig_basis(equispaced_angles(s, harmonics.dtype, harmonics.device), D)
        if s == 1:
            return (T[0] @ harmonics.reshape(2 * D + 1, -1)).view(rest)
        return harmonics[0]
    T = trig_basis(equispaced_angles(s, harmonics.dtype, harmonics.device), D)
    return _DiscreteMax.apply(harmonics.reshape(2 * D + 1, -1), T).view(rest)


def continuous_max(harmonics: Tensor, grid: int | None = None, newton_steps: int = 3, return_angle: bool = False):
    """Maximum of each trigonometric polynomial over the whole circle.

    Degree 1 is closed-form: ``max = A_0 + |(A_1, B_1)|`` at ``φ* = atan2(B_1, A_1)``. Higher degrees:
    sample ``grid`` equispaced angles (default ``max(32, 12 D)``); take two candidates, the best grid angle
    and the best one at least three grid steps away from it (a second peak); move each to the vertex of the
    parabola through its grid neighbours, then ``newton_steps`` Newton steps on ``resp'(φ) = 0`` (where
    ``resp'' >= 0`` a quarter grid step uphill instead; steps clipped to one grid spacing); keep the better
    candidate, never worse than its grid value. The value is ``resp(φ*)`` with ``φ*`` held constant, which
    is the exact gradient of the maximum since ``resp'(φ*) = 0``.

    The result is the true maximum to float rounding unless three local maxima are within the grid error
    ``max|resp''| (π / grid)^2 / 2`` of each other, in which case it is within that error of it.

    Args:
        harmonics: ``(2 D + 1, *rest)`` harmonic layout (unfolded: the true polynomial, not aliased samples).
        grid: number of grid angles (``D >= 2``).
        newton_steps: refinement steps after the parabolic step (``D >= 2``).
        return_angle: also return ``φ*`` (``rest``-shaped, no gradient).

    Returns:
        ``rest``-shaped maxima (and the maximising angles if ``return_angle``).
    """
    D = harmonic_degree(harmonics)
    rest = harmonics.shape[1:]
    H2 = harmonics.reshape(2 * D + 1, -1)
    if D == 0:
        value = H2[0].view(rest)
        zeros = torch.zeros(rest, dtype=harmonics.dtype, device=harmonics.device)
        return (value, zeros) if return_angle else value
    grid = max(32, 12 * D) if grid is None else int(grid)
    if grid < 8:
        raise ValueError(f"continuous_max needs a grid of at least 8 angles, got {grid}")
    with torch.no_grad():
        Hd = H2.detach()
        phi = torch.atan2(Hd[2], Hd[1]) if D == 1 else _maximising_angle(Hd, D, grid, newton_steps)
    value = _ValueAtAngle.apply(H2, phi).view(rest)
    return (value, phi.view(rest)) if return_angle else value


def _grid_candidates(Hd: Tensor, D: int, grid: int):
    """Per column of ``Hd`` (t, M): the two candidate angles after the parabolic step, their grid values
    and grid angles, each ``(2, M)``. Columns are processed in chunks with the angles along the rows."""
    dev, dt = Hd.device, Hd.dtype
    TT = trig_basis(equispaced_angles(grid, dt, dev), D).t().contiguous()  # (t, grid)
    M = Hd.shape[1]
    spacing = 2.0 * math.pi / grid
    phi, at_grid, grid_angle = (torch.empty(2, M, dtype=dt, device=dev) for _ in range(3))
    chunk = max(1, _CHUNK_ELEMENTS // grid)
    near = torch.arange(-2, 3, device=dev)
    for start in range(0, M, chunk):
        stop = min(M, start + chunk)
        S = Hd[:, start:stop].t() @ TT  # (c, grid): each column's samples contiguous
        first = S.argmax(1, keepdim=True)
        excluded = S.scatter(1, (first + near).remainder(grid), -math.inf)
        second = excluded.argmax(1, keepdim=True)
        idx = torch.cat([first, second], dim=1)  # (c, 2)
        sa = S.gather(1, idx)
        sl = S.gather(1, (idx - 1).remainder(grid))
        sr = S.gather(1, (idx + 1).remainder(grid))
        curv = sl - 2.0 * sa + sr
        offset = torch.where(curv < 0, 0.5 * (sl - sr) / torch.where(curv < 0, curv, -1.0), 0.0)
        phi[:, start:stop] = ((idx.to(dt) + offset.clamp(-0.5, 0.5)) * spacing).t()
        at_grid[:, start:stop] = sa.t()
        grid_angle[:, start:stop] = (idx.to(dt) * spacing).t()
    return phi, at_grid, grid_angle


def _maximising_angle(Hd: Tensor, D: int, grid: int, newton_steps: int) -> Tensor:
    """``φ*`` per column of ``Hd`` (t, M), degree ``D >= 2`` (grid, parabola, Newton; see
    :func:`continuous_max`)."""
    spacing = 2.0 * math.pi / grid
    phi, at_grid, grid_angle = _grid_candidates(Hd, D, grid)
    for _ in range(newton_steps):
        _, d1, d2 = _poly_and_derivatives(Hd, phi, D)
        concave = d2 < 0
        step = torch.where(concave, -d1 / torch.where(concave, d2, -1.0), torch.sign(d1) * (spacing / 4))
        phi = phi + step.clamp(-spacing, spacing)
    refined, _, _ = _poly_and_derivatives(Hd, phi, D, derivatives=False)
    better = refined >= at_grid
    phi = torch.where(better, phi, grid_angle)
    refined = torch.where(better, refined, at_grid)
    return torch.where(refined[0] >= refined[1], phi[0], phi[1])


def angular_pool(responses: Tensor, mode: str, dim: int = 1) -> Tensor:
    """Pool responses already sampled at ``s`` equispaced angles.

    Args:
        responses: e.g. ``(N, s, C)`` with the angle axis at ``dim``.
        mode: ``"max"``, ``"mean"`` or ``"none"`` (``"continuous"`` needs harmonics: use
            :func:`continuous_max`).

    Returns:
        ``(N, C)`` for max/mean, the input unchanged for none.
    """
    if mode == "max":
        return responses.amax(dim=dim)
    if mode == "mean":
        return responses.mean(dim=dim)
    if mode == "none":
        return responses
    raise ValueError(f"angular_pool: mode must be 'max', 'mean' or 'none' for sampled responses, got {mode!r}")
