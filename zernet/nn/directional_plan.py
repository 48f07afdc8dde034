r"""The per-layer plan of a direction-preserving convolution: which input harmonics feed which outputs.

A :class:`~zernet.nn.directional.DirectionalZernikeConv` maps the transported Zernike coefficients
``α_p[x, c]`` (``x = j (2 L_in + 1) + r``: Zernike basis ``j``, Fourier entry ``r`` of the input's direction
axis) to the output ``y_p[t, o] = Σ_{x, c} α_p[x, c] W[x, c, t, o]`` with ``W[x, c, t, o] = Σ_y E[x, y, t]
G[y, c, o]`` and the fixed coupling ``E`` (:func:`coupling_tensor`). ``E`` is very sparse: in the complex
basis of :func:`zernet.fourier.harmonic_basis` (and its Zernike analogue) a rotation is diagonal, so the
input harmonic ``(m_j, ℓ_r)`` (signed orders) only reaches the output order ``m_j + ℓ_r``. In the real
layouts the input pair ``(|m|, ℓ)`` reaches output orders ``|m| + ℓ`` and ``||m| - ℓ|`` only.

A :class:`DirectionalPlan` records, for one layer shape ``(n_max, L_in, output)``:

* ``inputs``: the input harmonics ``x`` the output needs at all, in the order the directional operator
  returns them (:meth:`zernet.operators.DirectionalOperator.apply_harmonic`): with ``L_out = 1``
  (``L_in = 1``, ``n_max = 5``) that is 35 of the 63, so the operator never computes the other 28;
* ``blocks``: per output block (Fourier order ``μ``: slabs ``cos μφ, sin μφ``; or all ``s`` samples), the
  positions of its inputs in ``inputs`` (a contiguous range whenever possible, so no gather is needed);
* the non-zero couplings ``(position in W, kernel row y, value)`` from which :func:`harmonic_weights`
  assembles every block's dense weight from the kernel ``G``.

:func:`plan_contraction` then computes the whole output with one dense product per block.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
import torch
from torch import Tensor

from zernet.fourier import fourier_dim, fourier_rotation_matrix, sample_angles, trig_table
from zernet.zernike import num_bases, rotation_matrix

__all__ = [
    "coupling_tensor",
    "PlanBlock",
    "DirectionalPlan",
    "directional_plan",
    "harmonic_weights",
    "plan_contraction",
]


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
        return np.moveaxis(_coupling(n_max, in_order, sample_angles(samples)), 0, -1)
    degree = max(n_max + in_order, out_order)
    grid = 2 * degree + 1  # exact DFT of a trigonometric polynomial of this degree
    values = _coupling(n_max, in_order, sample_angles(grid))  # (grid, X, Y)
    table = trig_table(sample_angles(grid), out_order)  # (grid, T)
    weights = np.full(fourier_dim(out_order), 2.0 / grid)
    weights[0] = 1.0 / grid
    out = np.einsum("bxy,bt->xyt", values, table * weights)
    out[np.abs(out) < 1e-13] = 0.0
    return out


@dataclass(frozen=True)
class PlanBlock:
    """One output block: slabs ``[t0, t1)`` from the inputs at ``positions`` (indices into ``plan.inputs``).

    ``start``/``stop``: the same positions as a contiguous range (``start = -1`` when they are not one, and
    the block gathers them); ``offset``: first row of this block's weight in the stacked weight rows.
    """

    t0: int
    t1: int
    positions: tuple
    start: int
    stop: int
    offset: int


@dataclass(frozen=True, eq=False)
class DirectionalPlan:
    """Which input harmonics a layer needs and how they couple to its outputs (module docstring).

    Attributes:
        n_max, in_order: the layer's Zernike degree and input Fourier order ``L_in``.
        output: ``"fourier"`` or ``"samples"``; ``out_dim``: ``2 L_out + 1`` or ``s``.
        inputs: input harmonics ``x = j (2 L_in + 1) + r`` to compute, in operator order.
        blocks: :class:`PlanBlock` per output block, in slab order.
        weight_rows: rows ``Σ_b n_b T_b`` of the stacked block weights.
        entry_pos, entry_y, entry_val: the non-zero couplings: stacked weight row, kernel row ``y``,
            value (numpy int64 / float64).
    """

    n_max: int
    in_order: int
    output: str
    out_dim: int
    inputs: tuple
    blocks: tuple
    weight_rows: int
    entry_pos: np.ndarray
    entry_y: np.ndarray
    entry_val: np.ndarray
    _tensors: dict = field(default_factory=dict, repr=False)

    @property
    def k(self) -> int:
        return num_bases(self.n_max)

    @property
    def disjoint(self) -> bool:
        """Every input feeds exactly one block through a contiguous range (no gather, no sum)."""
        return all(b.start >= 0 for b in self.blocks) and sum(len(b.positions) for b in self.blocks) == len(self.inputs)

    def entry_tensors(self, device) -> tuple[Tensor, Tensor, Tensor]:
        """``(entry_pos, entry_y, entry_val)`` as torch tensors on ``device`` (kept)."""
        device = torch.device(device)
        if device not in self._tensors:
            self._tensors[device] = (
                torch.from_numpy(self.entry_pos).to(device),
                torch.from_numpy(self.entry_y).to(device),
                torch.from_numpy(self.entry_val).to(device),
            )
        return self._tensors[device]


def _slab_ranges(output: str, out_dim: int) -> list[tuple[int, int]]:
    if output == "samples":
        return [(0, out_dim)]
    order = (out_dim - 1) // 2
    return [(0, 1)] + [(2 * mu - 1, 2 * mu + 1) for mu in range(1, order + 1)]


@lru_cache(maxsize=None)
def directional_plan(
    n_max: int, in_order: int, out_order: int | None = None, samples: int | None = None
) -> DirectionalPlan:
    """The plan of a layer with Zernike degree ``n_max`` and input order ``L_in`` whose output is its
    Fourier coefficients up to ``out_order`` or its values at ``samples`` angles (exactly one; cached)."""
    coupling = coupling_tensor(n_max, in_order, out_order=out_order, samples=samples)
    output = "fourier" if samples is None else "samples"
    out_dim = coupling.shape[2]
    inputs: list[int] = []
    where: dict[int, int] = {}
    per_block = []
    for t0, t1 in _slab_ranges(output, out_dim):
        sub = coupling[:, :, t0:t1]
        xs = np.flatnonzero(np.abs(sub).sum(axis=(1, 2)) > 0)
        for x in xs:
            if int(x) not in where:
                where[int(x)] = len(inputs)
                inputs.append(int(x))
        per_block.append((t0, t1, sorted(where[int(x)] for x in xs)))
    blocks, pos_parts, y_parts, val_parts = [], [], [], []
    offset = 0
    for t0, t1, positions in per_block:
        xs = np.asarray([inputs[i] for i in positions], dtype=np.int64)
        contiguous = len(positions) > 0 and positions == list(range(positions[0], positions[0] + len(positions)))
        start, stop = (positions[0], positions[0] + len(positions)) if contiguous else (-1, -1)
        blocks.append(PlanBlock(t0, t1, tuple(positions), start, stop, offset))
        sub = coupling[xs, :, t0:t1] if len(xs) else np.zeros((0, coupling.shape[1], t1 - t0))
        ix, iy, it = np.nonzero(sub)
        pos_parts.append(offset + ix * (t1 - t0) + it)
        y_parts.append(iy)
        val_parts.append(sub[ix, iy, it])
        offset += len(xs) * (t1 - t0)
    cat = lambda parts, dtype: np.ascontiguousarray(np.concatenate(parts).astype(dtype))  # noqa: E731
    return DirectionalPlan(
        n_max=int(n_max),
        in_order=int(in_order),
        output=output,
        out_dim=int(out_dim),
        inputs=tuple(inputs),
        blocks=tuple(blocks),
        weight_rows=int(offset),
        entry_pos=cat(pos_parts, np.int64),
        entry_y=cat(y_parts, np.int64),
        entry_val=cat(val_parts, np.float64),
    )


def harmonic_weights(weight: Tensor, plan: DirectionalPlan) -> list[Tensor]:
    """Every block's dense weight ``W_b`` ``(n_b C_in, T_b C_out)``, rows ``(input, c)``, columns ``(t, o)``.

    ``W[x, c, t, o] = Σ_y E[x, y, t] G[y, c, o]`` over the plan's non-zero couplings only (differentiable in
    ``weight``).

    Args:
        weight: the kernel ``G`` ``(k, 2 L_in + 1, C_in, C_out)``.
        plan: from :func:`directional_plan`.
    """
    c_in, c_out = weight.shape[-2], weight.shape[-1]
    pos, ys, vals = plan.entry_tensors(weight.device)
    g = weight.reshape(-1, c_in * c_out)
    contribution = vals.to(g.dtype)[:, None] * g.index_select(0, ys)
    stacked = g.new_zeros(plan.weight_rows, c_in * c_out).index_add(0, pos, contribution)
    out = []
    for b in plan.blocks:
        nb, tb = len(b.positions), b.t1 - b.t0
        w = stacked[b.offset : b.offset + nb * tb].view(nb, tb, c_in, c_out).permute(0, 2, 1, 3)
        out.append(w.reshape(nb * c_in, tb * c_out))
    return out


def _block_input(alpha: Tensor, block: PlanBlock, index: Tensor | None) -> Tensor:
    """``(N, n_b C_in)``: a view of the block's contiguous range, else a gather."""
    n = alpha.shape[0]
    if block.start >= 0:
        return alpha[:, block.start : block.stop].reshape(n, -1)
    return alpha.index_select(1, index).reshape(n, -1)


class _PlanContraction(torch.autograd.Function):
    """``α (N, X, C_in)`` and the block weights -> ``y (N, T, C_out)``: one dense product per block, with
    the gradients written block by block (no zero-filled full-size buffers when the blocks are disjoint)."""

    @staticmethod
    def forward(ctx, alpha: Tensor, plan: DirectionalPlan, *weights: Tensor) -> Tensor:
        n, _, c_in = alpha.shape
        c_out = weights[0].shape[1] // max(1, plan.blocks[0].t1 - plan.blocks[0].t0)
        out = alpha.new_empty(n, plan.out_dim, c_out)
        indices = [None if b.start >= 0 else torch.as_tensor(b.positions, device=alpha.device) for b in plan.blocks]
        for b, w, index in zip(plan.blocks, weights, indices):
            if not b.positions:  # orders beyond n_max + L_in: identically zero
                out[:, b.t0 : b.t1].zero_()
                continue
            out[:, b.t0 : b.t1] = (_block_input(alpha, b, index) @ w).view(n, b.t1 - b.t0, c_out)
        ctx.plan, ctx.indices = plan, indices
        ctx.save_for_backward(alpha, *weights)
        return out

    @staticmethod
    def backward(ctx, grad: Tensor):
        alpha, *weights = ctx.saved_tensors
        plan: DirectionalPlan = ctx.plan
        n, x_dim, c_in = alpha.shape
        grad = grad.contiguous()
        d_alpha = None
        if ctx.needs_input_grad[0]:
            d_alpha = alpha.new_empty(alpha.shape) if plan.disjoint else alpha.new_zeros(alpha.shape)
        d_weights = []
        for i, (b, w, index) in enumerate(zip(plan.blocks, weights, ctx.indices)):
            wants_weight = ctx.needs_input_grad[2 + i]
            if not b.positions:
                d_weights.append(torch.zeros_like(w) if wants_weight else None)
                continue
            g = grad[:, b.t0 : b.t1].reshape(n, -1)
            if d_alpha is not None:
                d_block = (g @ w.t()).view(n, -1, c_in)
                if b.start >= 0 and plan.disjoint:
                    d_alpha[:, b.start : b.stop] = d_block
                elif b.start >= 0:
                    d_alpha[:, b.start : b.stop] += d_block
                else:
                    d_alpha.index_add_(1, index, d_block)
            d_weights.append(_block_input(alpha, b, index).t() @ g if wants_weight else None)
        return (d_alpha, None, *d_weights)


def plan_contraction(alpha: Tensor, weights: list[Tensor], plan: DirectionalPlan) -> Tensor:
    """The layer's output without bias.

    Args:
        alpha: ``(N, len(plan.inputs), C_in)``, the input harmonics in plan order
            (:meth:`~zernet.operators.DirectionalOperator.apply_harmonic`).
        weights: :func:`harmonic_weights` of the kernel.
        plan: from :func:`directional_plan`.

    Returns:
        ``(N, plan.out_dim, C_out)``.
    """
    if alpha.dim() != 3 or alpha.shape[1] != len(plan.inputs):
        raise ValueError(f"plan_contraction: expected alpha (N, {len(plan.inputs)}, C_in), got {tuple(alpha.shape)}")
    return _PlanContraction.apply(alpha, plan, *weights)
