"""The per-layer plan of the direction-preserving convolution (zernet/nn/directional_plan.py), the
operator's apply_harmonic, the model's final_order, and the closed-form continuous max of degree 1."""

from functools import partial

import numpy as np
import pytest
import scipy.sparse as sp
import torch
from meshes import patch_like_operator

from zernet.fourier import fourier_dim, rotate_fourier
from zernet.nn.directional import DirectionalPooling, DirectionalZernikeConv
from zernet.nn.directional_plan import coupling_tensor, directional_plan, harmonic_weights, plan_contraction
from zernet.nn.models import DirectionalZerNet
from zernet.nn.pooling import continuous_max
from zernet.nn.reference import MatrixOperator
from zernet.operators import Geometry, build_directional_operator
from zernet.operators.directional import patch_pairs
from zernet.zernike import num_bases, orders, rotate_coefficients

N_MAX = 3
K = num_bases(N_MAX)


pytestmark = pytest.mark.usefixtures("one_torch_thread")


_patch_like_operator = partial(patch_like_operator, K)


def _naive(alpha_full, weight, coupling):
    """o[p, t, o] = Σ_{x, y, c} α[p, x, c] G[y, c, o] E[x, y, t] (dense)."""
    g = weight.reshape(-1, weight.shape[-2], weight.shape[-1])
    return torch.einsum("pxc,yco,xyt->pto", alpha_full, g, torch.as_tensor(coupling))


def _expected_inputs(n_max, in_order, out_order):
    """Input harmonics (j, r) whose orders |m_j| ± ℓ_r reach an output order <= out_order."""
    m = np.abs(orders(n_max))
    ell = np.concatenate([[0], np.repeat(np.arange(1, in_order + 1), 2)])
    return {
        j * len(ell) + r
        for j in range(len(m))
        for r in range(len(ell))
        if min(m[j] + ell[r], abs(m[j] - ell[r])) <= out_order
    }


@pytest.mark.parametrize(
    "in_order,out_order,samples", [(1, 1, None), (1, 2, None), (2, 5, None), (0, 3, None), (1, None, 5)]
)
def test_plan_contraction_equals_the_dense_coupling(in_order, out_order, samples):
    torch.manual_seed(0)
    plan = directional_plan(N_MAX, in_order, out_order=out_order, samples=samples)
    coupling = coupling_tensor(N_MAX, in_order, out_order=out_order, samples=samples)
    d = fourier_dim(in_order)
    alpha = torch.randn(6, K * d, 3, dtype=torch.float64)
    weight = torch.randn(K, d, 3, 4, dtype=torch.float64)
    expected = _naive(alpha, weight, coupling)
    got = plan_contraction(alpha[:, list(plan.inputs)], harmonic_weights(weight, plan), plan)
    torch.testing.assert_close(got, expected, rtol=1e-12, atol=1e-12)
    # the plan leaves out exactly the inputs no output sees
    unused = sorted(set(range(K * d)) - set(plan.inputs))
    assert np.all(coupling[unused] == 0)
    assert np.all(np.abs(coupling[list(plan.inputs)]).sum(axis=(1, 2)) > 0)
    if samples is None:
        assert set(plan.inputs) == _expected_inputs(N_MAX, in_order, out_order)


def test_plan_prunes_the_low_order_layer():
    """n_max = 5, L = 1 -> L_out = 1: 35 of the 63 input harmonics, two disjoint contiguous blocks."""
    plan = directional_plan(5, 1, out_order=1)
    assert len(plan.inputs) == 35 and plan.disjoint
    assert [(b.t0, b.t1, len(b.positions)) for b in plan.blocks] == [(0, 1, 15), (1, 3, 20)]
    assert len(directional_plan(5, 1, out_order=6).inputs) == 63


@pytest.mark.parametrize("out_order", [1, 4])
def test_plan_contraction_gradcheck(out_order):
    torch.manual_seed(1)
    plan = directional_plan(N_MAX, 1, out_order=out_order)
    alpha = torch.randn(4, len(plan.inputs), 2, dtype=torch.float64, requires_grad=True)
    weight = torch.randn(K, 3, 2, 2, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, w: plan_contraction(a, harmonic_weights(w, plan), plan), (alpha, weight))


def test_apply_harmonic_selects_the_transported_fit():
    op = _patch_like_operator()
    dop = build_directional_operator(op, 2)
    x = torch.randn(op.n_vertices, 5, 3, dtype=torch.float64)
    full = dop.apply(x).reshape(op.n_vertices, K * 5, 3)
    harmonics = (0, 7, 6, 13, 21)
    torch.testing.assert_close(dop.apply_harmonic(x, harmonics), full[:, list(harmonics)], rtol=0, atol=1e-13)
    x.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: dop.apply_harmonic(t, harmonics), (x,))
    # the per-order phase matrices describe the same map (α_a = C a - S b, α_b = S a + C b)
    c, s = (m.toarray().reshape(op.n_vertices, K, 2, op.n_vertices)[:, :, i] for m in dop.phases[1:2] for i in (0, 1))
    a, b = x[:, 3].detach().numpy(), x[:, 4].detach().numpy()
    np.testing.assert_allclose(
        full[:, 3::5].detach().numpy(), np.einsum("pjq,qc->pjc", c, a) - np.einsum("pjq,qc->pjc", s, b), atol=1e-12
    )


def test_patch_pairs_fast_path_equals_the_sort():
    op = _patch_like_operator(seed=3)
    pairs = patch_pairs(op.matrix, K)
    coo = op.matrix.tocoo()
    expected = np.unique(np.stack([coo.row // K, coo.col], axis=1), axis=0)
    np.testing.assert_array_equal(pairs, expected)
    random = MatrixOperator.random(12, K, nnz_per_row=4, seed=1)  # rows of a vertex differ: the general path
    coo = random.matrix.tocoo()
    np.testing.assert_array_equal(
        patch_pairs(random.matrix, K), np.unique(np.stack([coo.row // K, coo.col], axis=1), axis=0)
    )


def _gauge_transform(operator, delta):
    n = operator.matrix.shape[1]
    a = operator.matrix.toarray().reshape(n, K, n)
    turned = rotate_coefficients(a, delta[:, None], N_MAX, dim=1).reshape(n * K, n)
    c, s = np.cos(delta)[:, None], np.sin(delta)[:, None]
    frames = operator.frames.copy()
    frames[:, 0] = c * operator.frames[:, 0] + s * operator.frames[:, 1]
    frames[:, 1] = -s * operator.frames[:, 0] + c * operator.frames[:, 1]
    return MatrixOperator(sp.csr_matrix(turned), K, frames)


def test_final_order_one_model_is_gauge_invariant():
    torch.manual_seed(2)
    op = _patch_like_operator(n=16, seed=4, per_patch=7)
    delta = np.random.default_rng(5).uniform(-np.pi, np.pi, 16)
    model = DirectionalZerNet(3, 5, widths=(6, 6, 8, 10), k=K, nonlinearity="norm", final_order=1).eval()
    with torch.no_grad():
        for act in model.acts:
            act.norm_bias.uniform_(-0.5, 0.5)
    assert model.convs[-1].out_order == 1
    x = torch.randn(16, 3)
    y = model(x, Geometry([op]).with_directional(1))
    y_turned = model(x, Geometry([_gauge_transform(op, delta)]).with_directional(1))
    torch.testing.assert_close(y_turned, y, rtol=0, atol=5e-6 * y.abs().max().item())


def test_final_order_truncates_the_whole_response():
    torch.manual_seed(3)
    op = build_directional_operator(_patch_like_operator(), 1)
    full = DirectionalZernikeConv(2, 3, n_max=N_MAX, order=1, out_order=N_MAX + 1).double()
    low = DirectionalZernikeConv(2, 3, n_max=N_MAX, order=1, out_order=1).double()
    low.load_state_dict(full.state_dict())
    x = torch.randn(op.n_vertices, 3, 2, dtype=torch.float64)
    y_full, y_low = full(x, op), low(x, op)
    torch.testing.assert_close(y_low, y_full[:, :3], rtol=0, atol=1e-13)
    # and its output turns by δ_p like every order of the full response
    delta = torch.full((op.n_vertices, 1), 0.8, dtype=torch.float64)
    torch.testing.assert_close(rotate_fourier(y_low, delta, dim=1), rotate_fourier(y_full, delta, dim=1)[:, :3])


def test_continuous_max_degree_one_is_closed_form():
    torch.manual_seed(4)
    h = torch.randn(3, 50, 2, dtype=torch.float64)
    value, angle = continuous_max(h, return_angle=True)
    torch.testing.assert_close(value, h[0] + torch.hypot(h[1], h[2]), rtol=0, atol=1e-13)
    torch.testing.assert_close(h[1] * torch.cos(angle) + h[2] * torch.sin(angle), torch.hypot(h[1], h[2]))
    dense = torch.linspace(0, 2 * np.pi, 4001, dtype=torch.float64)[:, None, None]
    sampled = (h[0] + h[1] * torch.cos(dense) + h[2] * torch.sin(dense)).amax(0)
    assert torch.all(value >= sampled - 1e-12) and torch.all(value - sampled < 1e-5)
    h.requires_grad_(True)
    assert torch.autograd.gradcheck(continuous_max, (h,))
    assert torch.autograd.gradcheck(
        DirectionalPooling("continuous"), (h.detach().transpose(0, 1).clone().requires_grad_(True),)
    )


def test_a_batch_reuses_the_surfaces_matrices_and_matches_a_direct_build():
    """Geometry.concatenate's directional operator stacks its surfaces' kept matrices block-diagonally;
    values and gradients equal those of an operator built on the concatenated surfaces."""
    ops = [_patch_like_operator(n=9, seed=6), _patch_like_operator(n=7, seed=7)]
    parts = [build_directional_operator(op, 1) for op in ops]
    batch = Geometry.concatenate([Geometry([op], directional=[d]) for op, d in zip(ops, parts)]).directional[0]
    direct = build_directional_operator(MatrixOperator.concatenate(ops), 1)
    harmonics = directional_plan(N_MAX, 1, out_order=1).inputs
    x = torch.randn(16, 3, 2, dtype=torch.float64, requires_grad=True)
    y_batch, y_direct = batch.apply_harmonic(x, harmonics), direct.apply_harmonic(x, harmonics)
    torch.testing.assert_close(y_batch, y_direct, rtol=0, atol=1e-13)
    g = torch.randn_like(y_batch)
    (grad_batch,) = torch.autograd.grad(y_batch, x, g)
    (grad_direct,) = torch.autograd.grad(y_direct, x, g)
    torch.testing.assert_close(grad_batch, grad_direct, rtol=0, atol=1e-13)
    assert all(any(key[0] == tuple(harmonics) for key in part._torch) for part in parts)  # kept on the surfaces
