"""Tests for the direction-preserving (gauge-equivariant) Zernike convolution, zernet/nn/directional.py.

Gauge-change convention used throughout (module docstrings of zernet.nn.directional and zernet.operators.directional):
turning vertex p's frame by δ_p, i.e. ``e1 ← cos δ e1 + sin δ e2``, ``e2 ← -sin δ e1 + cos δ e2``,

* changes p's polar angles to θ - δ_p, so the Zernike coefficients of every patch field at p become
  those of f(r, θ + δ_p): operator rows of p are ``rotate_coefficients(·, +δ_p)``;
* changes a directional channel at q to h_q(ψ + δ_q): ``rotate_fourier(·, +δ_q)``;
* changes the transport angles to γ_qp + δ_q - δ_p (computed by zernet.geometry.polar.transport_angles from the
  turned frames, not supplied by hand);
* and must turn every output at p into o_p(φ + δ_p): ``rotate_fourier(·, +δ_p)`` on Fourier outputs, a
  cyclic shift by a on s samples when δ_p = 2π a / s, and no change at all after continuous pooling.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.sparse as sp
import torch
from meshes import random_frames

import zernet.operators.directional as directional_operators
from zernet.fourier import fourier_rotation_matrix, fourier_to_samples, rotate_fourier, samples_to_fourier, trig_table
from zernet.geometry import transport_angles
from zernet.nn.conv import ZernikeConv
from zernet.nn.directional import (
    DirectionalLayerNorm,
    DirectionalLifting,
    DirectionalPooling,
    DirectionalReLU,
    DirectionalZernikeConv,
)
from zernet.nn.models import DirectionalZerNet
from zernet.nn.reference import MatrixOperator
from zernet.operators import Geometry, build_directional_operator
from zernet.zernike import num_bases, rotate_coefficients, zernike_basis

N_MAX = 3
K = num_bases(N_MAX)


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _synthetic_operator(n=14, seed=0, density=0.35):
    """A patch operator with random sparse fit rows and random right-handed frames."""
    rng = np.random.default_rng(seed)
    matrix = sp.random(n * K, n, density=density, random_state=seed, format="csr")
    matrix.data = rng.normal(size=matrix.nnz)
    return MatrixOperator(matrix, K, random_frames(rng, n))


def _turn_frames(frames, delta):
    c, s = np.cos(delta)[:, None], np.sin(delta)[:, None]
    out = frames.copy()
    out[:, 0] = c * frames[:, 0] + s * frames[:, 1]
    out[:, 1] = -s * frames[:, 0] + c * frames[:, 1]
    return out


def _gauge_transform(operator, delta):
    """The same surface seen with every frame turned by δ_p: rows rotated by +δ_p, frames turned."""
    n = operator.matrix.shape[1]
    a = operator.matrix.toarray().reshape(n, K, n)
    turned = rotate_coefficients(a, delta[:, None], N_MAX, dim=1).reshape(n * K, n)
    return MatrixOperator(sp.csr_matrix(turned), K, _turn_frames(operator.frames, delta))


def _per_vertex(delta, dtype=torch.float64):
    return torch.as_tensor(delta, dtype=dtype)[:, None]


# ------------------------------------------------------------------------------------ circle functions


def test_fourier_samples_round_trip_and_rotation():
    torch.manual_seed(0)
    L, s = 3, 9
    c = torch.randn(5, 2 * L + 1, 2, dtype=torch.float64)
    samples = fourier_to_samples(c, s, dim=1)
    assert samples.shape == (5, s, 2)
    torch.testing.assert_close(samples_to_fourier(samples, L, dim=1), c)
    # direct evaluation of h(ψ) = a0 + Σ a cos ℓψ + b sin ℓψ
    psi = 2 * math.pi * 4 / s
    direct = c[:, 0] + sum(
        c[:, 2 * order - 1] * math.cos(order * psi) + c[:, 2 * order] * math.sin(order * psi)
        for order in range(1, L + 1)
    )
    torch.testing.assert_close(samples[:, 4], direct)
    # rotate_fourier(·, δ) gives h(ψ + δ); by 2π a / s it is a cyclic shift of the samples
    delta = 0.37
    rotated = fourier_to_samples(rotate_fourier(c, delta, dim=1), 1, dim=1)[:, 0]
    at_delta = fourier_to_samples(rotate_fourier(c, 0.0, dim=1), 1, dim=1)  # h(0)
    assert at_delta.shape == (5, 1, 2)
    direct = c[:, 0] + sum(
        c[:, 2 * order - 1] * math.cos(order * delta) + c[:, 2 * order] * math.sin(order * delta)
        for order in range(1, L + 1)
    )
    torch.testing.assert_close(rotated, direct)
    shifted = fourier_to_samples(rotate_fourier(c, 2 * math.pi * 2 / s, dim=1), s, dim=1)
    torch.testing.assert_close(shifted, torch.roll(samples, -2, dims=1))
    with pytest.raises(ValueError):
        samples_to_fourier(samples[:, :6], L, dim=1)  # 6 samples cannot hold order 3


def test_fourier_rotation_matrix_is_a_group_action():
    L = 2
    a, b = 0.4, -1.3
    qa, qb = fourier_rotation_matrix(a, L), fourier_rotation_matrix(b, L)
    np.testing.assert_allclose(qa @ qb, fourier_rotation_matrix(a + b, L), atol=1e-14)
    np.testing.assert_allclose(qa @ qa.T, np.eye(2 * L + 1), atol=1e-14)
    torch.testing.assert_close(fourier_rotation_matrix(torch.tensor(a, dtype=torch.float64), L), torch.as_tensor(qa))


# ------------------------------------------------------------------------------------ transported operator


@pytest.mark.parametrize("order", [0, 1, 3])
def test_directional_operator_is_the_transported_fit(order):
    op = _synthetic_operator()
    dop = build_directional_operator(op, order)
    assert not hasattr(op, "_zernet_directional_operators")  # a pure function: nothing is attached to op
    n = op.n_vertices
    assert dop.order == order and len(dop.phases) == order
    assert all(m.shape == (2 * n * K, n) and m.nnz == 2 * op.matrix.nnz for m in dop.phases)
    torch.manual_seed(1)
    x = torch.randn(n, 2 * order + 1, 3, dtype=torch.float64)
    alpha = dop.apply(x)
    assert alpha.shape == (n, K, 2 * order + 1, 3)
    # Dense reference: α_p(j, ℓ) = Σ_q A[(p,j), q] ĥ_q(ℓ) e^{-iℓγ_qp}, ĥ(ℓ) = (a_ℓ - i b_ℓ) / 2.
    a = op.matrix.toarray().reshape(n, K, n)
    p, q = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    gamma = transport_angles(op.frames, p.ravel(), q.ravel()).reshape(n, n)
    xn = x.numpy()
    np.testing.assert_allclose(alpha[:, :, 0].numpy(), np.einsum("pjq,qc->pjc", a, xn[:, 0]), atol=1e-12)
    for ell in range(1, order + 1):
        h = xn[:, 2 * ell - 1] - 1j * xn[:, 2 * ell]
        expected = np.einsum("pjq,pq,qc->pjc", a, np.exp(-1j * ell * gamma), h)
        got = alpha[:, :, 2 * ell - 1].numpy() - 1j * alpha[:, :, 2 * ell].numpy()
        np.testing.assert_allclose(got, expected, atol=1e-12)


def test_directional_operator_gradcheck():
    op = _synthetic_operator(n=6, density=0.5)
    dop = build_directional_operator(op, 2)
    x = torch.randn(6, 5, 2, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(dop.apply, (x,))


# ------------------------------------------------------------------------------------ the convolution


def test_response_equals_the_integral_over_disk_and_circle():
    """o_p(φ) = ∫_D (1/2π)∫ F_p(r,θ;ψ) g(r, θ-φ; ψ-φ) dψ dA, by quadrature."""
    torch.manual_seed(2)
    op = _synthetic_operator()
    L = 2
    conv = DirectionalZernikeConv(3, 4, n_max=N_MAX, order=L, out_order=N_MAX + L, bias=False).double()
    x = torch.randn(op.n_vertices, 2 * L + 1, 3, dtype=torch.float64)
    dop = build_directional_operator(op, L)
    alpha = conv.fit(x, dop)[5].numpy()  # (k, 2L+1, C_in) at vertex 5
    out = conv(x, dop)[5].detach()  # (2(N_MAX+L)+1, C_out)
    G = conv.weight.detach().numpy()
    xr, wr = np.polynomial.legendre.leggauss(12)
    r, wr = (xr + 1) / 2, wr / 2
    n_theta, n_psi = 24, 16  # exact for the trigonometric degrees involved
    theta = np.arange(n_theta) * 2 * np.pi / n_theta
    psi = np.arange(n_psi) * 2 * np.pi / n_psi
    rr, tt = np.meshgrid(r, theta, indexing="ij")
    field = np.einsum("abj,sr,jrc->absc", zernike_basis(rr, tt, N_MAX), trig_table(psi, L), alpha)
    area = (wr * r)[:, None] * (2 * np.pi / n_theta)
    for phi in (0.0, 0.7, 2.9):
        kernel = np.einsum("abj,sr,jrco->absco", zernike_basis(rr, tt - phi, N_MAX), trig_table(psi - phi, L), G)
        integral = np.einsum("absc,absco,ab->o", field, kernel, area) / n_psi
        value = torch.as_tensor(trig_table(np.array([phi]), N_MAX + L)) @ out
        np.testing.assert_allclose(value[0].numpy(), integral, rtol=1e-10, atol=1e-10)


def test_samples_output_is_the_fourier_output_sampled():
    torch.manual_seed(3)
    op = _synthetic_operator()
    L, s = 1, 8
    full = DirectionalZernikeConv(2, 3, n_max=N_MAX, order=L, out_order=N_MAX + L).double()
    sampled = DirectionalZernikeConv(2, 3, n_max=N_MAX, order=L, output="samples", angular_resolution=s).double()
    sampled.load_state_dict(full.state_dict())
    with torch.no_grad():
        full.bias.normal_()
        sampled.bias.copy_(full.bias)
    x = torch.randn(op.n_vertices, 2 * L + 1, 2, dtype=torch.float64)
    op = build_directional_operator(op, L)
    torch.testing.assert_close(sampled(x, op), fourier_to_samples(full(x, op), s, dim=1))
    # truncating the output order keeps exactly the low orders of the full response
    low = DirectionalZernikeConv(2, 3, n_max=N_MAX, order=L, out_order=2).double()
    low.load_state_dict(full.state_dict())
    torch.testing.assert_close(low(x, op), full(x, op)[:, :5])


@pytest.mark.parametrize("order", [1, 2])
def test_layer_is_gauge_equivariant(order):
    """Random frame turns δ_p: Fourier order ℓ at p turns by ℓ δ_p; continuous max unchanged."""
    torch.manual_seed(4)
    op = _synthetic_operator(seed=order)
    n = op.n_vertices
    delta = np.random.default_rng(5).uniform(-np.pi, np.pi, n)
    op, op_turned = (build_directional_operator(o, order) for o in (op, _gauge_transform(op, delta)))
    conv = DirectionalZernikeConv(3, 4, n_max=N_MAX, order=order, out_order=N_MAX + order)
    x = torch.randn(n, 2 * order + 1, 3)
    x_turned = rotate_fourier(x, _per_vertex(delta, x.dtype), dim=1)
    y, y_turned = conv(x, op), conv(x_turned, op_turned)
    expected = rotate_fourier(y, _per_vertex(delta, y.dtype), dim=1)
    scale = y.abs().max().item()
    torch.testing.assert_close(y_turned, expected, rtol=0, atol=2e-6 * scale)
    pool = DirectionalPooling("continuous")
    torch.testing.assert_close(pool(y_turned), pool(y), rtol=0, atol=2e-6 * scale)
    # the same in float64 is exact to float64 rounding
    conv64 = conv.double()
    x64 = x.double()
    y64, y64_turned = conv64(x64, op), conv64(rotate_fourier(x64, _per_vertex(delta), dim=1), op_turned)
    torch.testing.assert_close(y64_turned, rotate_fourier(y64, _per_vertex(delta), dim=1), rtol=0, atol=1e-12 * scale)
    torch.testing.assert_close(pool(y64_turned), pool(y64), rtol=0, atol=1e-12 * scale)


def test_equivariance_needs_the_transport(monkeypatch):
    """Without aligning neighbouring frames (γ ≡ 0, the authors' release) the test above fails."""
    torch.manual_seed(6)
    op = _synthetic_operator()
    n = op.n_vertices
    delta = np.random.default_rng(7).uniform(-np.pi, np.pi, n)
    op_turned = _gauge_transform(op, delta)
    monkeypatch.setattr(directional_operators, "transport_angles", lambda frames, p, q: np.zeros(len(p)))
    op, op_turned = (build_directional_operator(o, 1) for o in (op, op_turned))
    conv = DirectionalZernikeConv(2, 2, n_max=N_MAX, order=1, out_order=N_MAX + 1).double()
    x = torch.randn(n, 3, 2, dtype=torch.float64)
    y = conv(x, op)
    y_turned = conv(rotate_fourier(x, _per_vertex(delta), dim=1), op_turned)
    err = (y_turned - rotate_fourier(y, _per_vertex(delta), dim=1)).abs().max()
    assert err > 1e-2 * y.abs().max()


def test_discrete_rotations_shift_samples_exactly():
    """δ_p = 2π a_p / s: sampled outputs shift cyclically by a_p, discrete max pooling is unchanged."""
    torch.manual_seed(8)
    s = 4
    op = _synthetic_operator()
    n = op.n_vertices
    shift = np.random.default_rng(9).integers(0, s, n)
    delta = 2 * np.pi * shift / s
    op_turned = build_directional_operator(_gauge_transform(op, delta), 1)
    conv = DirectionalZernikeConv(3, 5, n_max=N_MAX, order=1, output="samples", angular_resolution=s)
    x = torch.randn(n, 3, 3)
    y = conv(x, build_directional_operator(op, 1))
    y_turned = conv(rotate_fourier(x, _per_vertex(delta, x.dtype), dim=1), op_turned)
    expected = torch.stack([torch.roll(y[p], -int(shift[p]), dims=0) for p in range(n)])
    scale = y.abs().max().item()
    torch.testing.assert_close(y_turned, expected, rtol=0, atol=2e-6 * scale)
    torch.testing.assert_close(y_turned.amax(1), y.amax(1), rtol=0, atol=2e-6 * scale)
    # contrast: a turn that is not a multiple of 2π/s changes the discrete max beyond rounding
    op_off = build_directional_operator(_gauge_transform(op, delta + 0.3), 1)
    y_off = conv(rotate_fourier(x, _per_vertex(delta + 0.3, x.dtype), dim=1), op_off)
    assert (y_off.amax(1) - y.amax(1)).abs().max() > 1e-3 * scale


def test_lifting_agrees_with_zernike_conv():
    """L_in = 0, ψ-independent kernel: o_p(φ) = ZernikeConv's resp_p(-φ); pooled outputs equal."""
    torch.manual_seed(10)
    s = 8
    op = _synthetic_operator()
    x = torch.randn(op.n_vertices, 3, dtype=torch.float64)
    ref = ZernikeConv(3, 4, n_max=N_MAX, angular_resolution=s, pooling="none").double()
    lift = DirectionalLifting(3, 4, n_max=N_MAX, output="samples", angular_resolution=s).double()
    with torch.no_grad():
        ref.bias.normal_()
        lift.weight.copy_(ref.weight[:, None])
        lift.bias.copy_(ref.bias)
    mine, theirs = lift(x, op), ref(x, op)
    torch.testing.assert_close(mine, theirs[:, (-torch.arange(s)) % s])
    # pooled: the whole response's continuous / discrete max equals ZernikeConv's
    full = DirectionalLifting(3, 4, n_max=N_MAX, out_order=N_MAX).double()
    full.load_state_dict(lift.state_dict())
    for mode, pooling in (("continuous", "continuous"), ("discrete", "max"), ("mean", "mean")):
        ref.pooling = pooling
        torch.testing.assert_close(DirectionalPooling(mode, angular_resolution=s)(full(x, op)), ref(x, op))
    # a directional layer fed only a_0 with a kernel without ψ-dependence computes the same
    conv = DirectionalZernikeConv(3, 4, n_max=N_MAX, order=2, output="samples", angular_resolution=s).double()
    with torch.no_grad():
        conv.weight.zero_()
        conv.weight[:, 0] = ref.weight
        conv.bias.copy_(ref.bias)
    x_dir = torch.zeros(op.n_vertices, 5, 3, dtype=torch.float64)
    x_dir[:, 0] = x
    ref.pooling = "none"
    torch.testing.assert_close(conv(x_dir, build_directional_operator(op, 2)), theirs[:, (-torch.arange(s)) % s])


def test_gradcheck_float64():
    torch.manual_seed(11)
    op = _synthetic_operator(n=6, density=0.5)
    conv = DirectionalZernikeConv(2, 2, n_max=N_MAX, order=1, out_order=2).double()
    op = build_directional_operator(op, 1)
    x = torch.randn(6, 3, 2, dtype=torch.float64, requires_grad=True)
    weight = conv.weight.detach().clone().requires_grad_(True)
    bias = torch.randn(2, dtype=torch.float64, requires_grad=True)

    def f(x, weight, bias):
        return torch.func.functional_call(conv, {"weight": weight, "bias": bias}, (x, op))

    assert torch.autograd.gradcheck(f, (x, weight, bias))
    relu = DirectionalReLU(2, 1, mode="norm").double()
    with torch.no_grad():
        relu.norm_bias.fill_(0.1)
    assert torch.autograd.gradcheck(relu, (x,))
    regular = DirectionalReLU(2, 1, mode="regular", angular_resolution=5)
    assert torch.autograd.gradcheck(regular, (x,))
    full = torch.randn(6, 9, 2, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(DirectionalPooling("continuous"), (full,))
    assert torch.autograd.gradcheck(DirectionalPooling("discrete", angular_resolution=4), (full,))


# ------------------------------------------------------------------------------------ model


def _model_invariance(nonlinearity, pooling, delta, s=4, seed=12, norm=None):
    torch.manual_seed(seed)
    op = _synthetic_operator(n=16, seed=seed)
    op_turned = _gauge_transform(op, delta)
    model = DirectionalZerNet(
        3, 5, widths=(6, 6, 8, 10), k=K, angular_resolution=s, pooling=pooling, nonlinearity=nonlinearity, norm=norm
    ).eval()
    if norm:
        with torch.no_grad():  # away from the identity initialisation, so the test sees the affine part
            for layer in model.norms:
                layer.weight.uniform_(0.5, 1.5)
                layer.bias.uniform_(-0.5, 0.5)
    if nonlinearity == "norm":
        with torch.no_grad():
            for act in model.acts:
                act.norm_bias.uniform_(-0.5, 0.5)
    x = torch.randn(16, 3)  # scalar input features are gauge-invariant
    order = model.directional_order
    y, y_turned = (
        model(x, Geometry([op]).with_directional(order)),
        model(x, Geometry([op_turned]).with_directional(order)),
    )
    return y, y_turned


def test_model_invariant_for_any_turn_with_norm_nonlinearity_and_continuous_pooling():
    delta = np.random.default_rng(13).uniform(-np.pi, np.pi, 16)
    y, y_turned = _model_invariance("norm", "continuous", delta)
    torch.testing.assert_close(y_turned, y, rtol=0, atol=5e-6 * y.abs().max().item())


def test_model_with_layer_norm_invariant_for_any_turn():
    delta = np.random.default_rng(16).uniform(-np.pi, np.pi, 16)
    y, y_turned = _model_invariance("norm", "continuous", delta, norm="layer")
    torch.testing.assert_close(y_turned, y, rtol=0, atol=5e-6 * y.abs().max().item())
    with pytest.raises(ValueError, match="equivariant"):
        DirectionalZerNet(3, 5, widths=(6, 10), k=K, norm="batch")


@pytest.mark.parametrize("order", [0, 1, 3])
def test_layer_norm_is_the_layer_norm_of_the_sampled_channels_and_commutes_with_turns(order):
    torch.manual_seed(17)
    n, c, samples = 6, 5, 64  # 64 > 2 * 2L angles sample the squares of an order-L function exactly
    norm = DirectionalLayerNorm(c).double()
    with torch.no_grad():
        norm.weight.uniform_(0.5, 1.5)
        norm.bias.uniform_(-1, 1)
    x = torch.randn(n, 2 * order + 1, c, dtype=torch.float64)
    y = norm(x)
    # the reference: a layer norm over all channels and directions of the sampled functions
    values = fourier_to_samples(x, samples, dim=1)  # (N, s, C)
    flat = values.reshape(n, -1)
    normalised = (flat - flat.mean(1, keepdim=True)) / torch.sqrt(flat.var(1, unbiased=False, keepdim=True) + norm.eps)
    expected = normalised.view(n, samples, c) * norm.weight + norm.bias
    torch.testing.assert_close(fourier_to_samples(y, samples, dim=1), expected, rtol=0, atol=1e-12)
    delta = torch.from_numpy(np.random.default_rng(18).uniform(-np.pi, np.pi, (n, 1)))
    torch.testing.assert_close(
        norm(rotate_fourier(x, delta, dim=1)), rotate_fourier(y, delta, dim=1), rtol=0, atol=1e-12
    )
    assert torch.autograd.gradcheck(norm, (x.clone().requires_grad_(),))
    with pytest.raises(ValueError, match="2L \\+ 1"):
        norm(torch.randn(n, 2, c, dtype=torch.float64))


def test_model_invariant_for_turns_by_multiples_of_2pi_over_s():
    s = 4
    delta = 2 * np.pi * np.random.default_rng(14).integers(0, s, 16) / s
    for nonlinearity in ("regular", "norm"):
        for pooling in ("discrete", "continuous", "mean"):
            y, y_turned = _model_invariance(nonlinearity, pooling, delta, s=s)
            torch.testing.assert_close(y_turned, y, rtol=0, atol=5e-6 * y.abs().max().item())


def test_model_shapes_batching_and_state_dict(tmp_path):
    torch.manual_seed(15)
    ops = [_synthetic_operator(n=10, seed=1), _synthetic_operator(n=7, seed=2)]
    model = DirectionalZerNet(3, 4, widths=(5, 6, 7), k=K).eval()
    x = [torch.randn(10, 3), torch.randn(7, 3)]
    geometries = [Geometry([op]).with_directional(model.directional_order) for op in ops]
    separate = torch.cat([model(xi, g) for xi, g in zip(x, geometries)])
    batched = model(torch.cat(x), Geometry([MatrixOperator.concatenate(ops)]).with_directional(model.directional_order))
    assert batched.shape == (17, 4)
    torch.testing.assert_close(batched, separate, rtol=1e-5, atol=1e-6)
    # concatenating the prepared geometries gives the same batch (block-diagonal directional operators)
    torch.testing.assert_close(model(torch.cat(x), Geometry.concatenate(geometries)), batched, rtol=1e-6, atol=1e-7)
    path = tmp_path / "model.pt"
    torch.save(model.state_dict(), path)
    clone = DirectionalZerNet(3, 4, widths=(5, 6, 7), k=K).eval()
    clone.load_state_dict(torch.load(path, weights_only=True))
    torch.testing.assert_close(clone(x[0], geometries[0]), model(x[0], geometries[0]))
    assert not any("coupling" in key for key in model.state_dict())  # fixed tensors are rebuilt, not saved


def test_layer_shapes_repr_and_errors():
    scalar_op = _synthetic_operator(n=9)
    op = build_directional_operator(scalar_op, 1)
    x = torch.randn(9, 3, 2)
    assert DirectionalZernikeConv(2, 5, n_max=N_MAX, order=1)(x, op).shape == (9, 3, 5)
    assert DirectionalZernikeConv(2, 5, n_max=N_MAX, order=1, out_order=4)(x, op).shape == (9, 9, 5)
    assert DirectionalZernikeConv(2, 5, n_max=N_MAX, order=1, output="samples", angular_resolution=6)(x, op).shape == (
        9,
        6,
        5,
    )
    assert DirectionalLifting(2, 5, n_max=N_MAX, out_order=2)(x[:, 0], scalar_op).shape == (9, 5, 5)
    assert DirectionalPooling("mean")(x).shape == (9, 2)
    assert DirectionalReLU(2, 1)(x).shape == (9, 3, 2)
    text = repr(DirectionalZernikeConv(2, 5, n_max=N_MAX, order=1, out_order=4))
    assert "DirectionalZernikeConv(2, 5" in text and "order=1" in text and "out_order=4" in text
    with pytest.raises(ValueError):
        DirectionalZernikeConv(2, 5, n_max=N_MAX + 1, order=1)(x, op)  # k mismatch
    with pytest.raises(ValueError, match="build_directional_operator"):
        DirectionalZernikeConv(2, 5, n_max=N_MAX, order=1)(x, scalar_op)  # the layer never builds it itself
    with pytest.raises(ValueError):
        DirectionalZernikeConv(2, 5, n_max=N_MAX, order=2)(x, op)  # wrong direction axis
    with pytest.raises(ValueError):
        DirectionalReLU(2, 2, mode="regular", angular_resolution=4)  # s must exceed 2L


def test_registered_as_zernet_directional():
    from zernet.nn.models import build_model

    model = build_model("zernet-directional", 3, 4, widths=(5, 6), k=K, angular_resolution=4)
    assert isinstance(model, DirectionalZerNet)
    geometry = Geometry([_synthetic_operator(n=9)])
    assert model.directional_order == 1
    assert model(torch.randn(9, 3), geometry.with_directional(1)).shape == (9, 4)


# ------------------------------------------------------------------------------------ a real mesh


@pytest.fixture(scope="module")
def sphere_patches():
    """Polar coordinates and the patch operator of a 162-vertex icosphere (n_max = 3)."""
    trimesh = pytest.importorskip("trimesh")
    from zernet.geometry import Surface, compute_polar, sample_surface
    from zernet.operators import PatchConfig, assemble_operator

    mesh = trimesh.creation.icosphere(subdivisions=2)
    surface = Surface(
        vertices=np.asarray(mesh.vertices, dtype=np.float64), faces=np.asarray(mesh.faces, dtype=np.int64)
    )
    config = PatchConfig(r0=0.6, n_samples=1500, patch_size=30, n_max=N_MAX)
    samples = sample_surface(surface, config.n_samples, seed=0)
    polar = compute_polar(surface, samples, config.r0, backend="fast")

    def build(delta):
        """Assemble with every frame turned by δ_p: angles measured from the turned e1 are θ - δ_p."""
        angle = np.mod(polar.angle - delta[polar.center] + np.pi, 2 * np.pi) - np.pi
        frames = _turn_frames(polar.frames, delta)
        return assemble_operator(polar.center, polar.sample, polar.radius, angle, frames, samples.interpolation, config)

    return build, surface.vertices.shape[0]


def test_real_mesh_gauge_change_rotates_operator_rows(sphere_patches):
    """Rebuilding from turned frames equals rotating every vertex's rows by +δ_p (rotate_coefficients)."""
    build, n = sphere_patches
    delta = np.random.default_rng(16).uniform(-np.pi, np.pi, n)
    op, op_turned = build(np.zeros(n)), build(delta)
    algebraic = _gauge_transform(MatrixOperator(op.matrix, K, op.frames), delta)
    np.testing.assert_allclose(op_turned.matrix.toarray(), algebraic.matrix.toarray(), atol=1e-9)
    np.testing.assert_allclose(op_turned.frames, algebraic.frames, atol=1e-12)


def test_real_mesh_directional_model_is_invariant(sphere_patches):
    build, n = sphere_patches
    rng = np.random.default_rng(17)
    any_turn = rng.uniform(-np.pi, np.pi, n)
    quarter_turns = 2 * np.pi * rng.integers(0, 4, n) / 4
    op = build(np.zeros(n))
    torch.manual_seed(18)
    x = torch.randn(n, 3)
    for nonlinearity, pooling, delta in (("norm", "continuous", any_turn), ("regular", "discrete", quarter_turns)):
        model = DirectionalZerNet(3, 4, widths=(8, 8, 16), k=K, pooling=pooling, nonlinearity=nonlinearity).eval()
        if nonlinearity == "norm":
            with torch.no_grad():
                model.acts[0].norm_bias.uniform_(-0.5, 0.5)
        order = model.directional_order
        y, y_turned = (
            model(x, Geometry([op]).with_directional(order)),
            model(x, Geometry([build(delta)]).with_directional(order)),
        )
        torch.testing.assert_close(y_turned, y, rtol=0, atol=5e-6 * y.abs().max().item())
    # the transported fit on the mesh: order-1 Fourier coefficients at p turn by δ_p
    conv = DirectionalZernikeConv(3, 4, n_max=N_MAX, order=1, out_order=2).double()
    h = torch.randn(n, 3, 3, dtype=torch.float64)
    d = _per_vertex(any_turn)
    y = conv(h, build_directional_operator(op, 1))
    y_turned = conv(rotate_fourier(h, d, dim=1), build_directional_operator(build(any_turn), 1))
    torch.testing.assert_close(y_turned, rotate_fourier(y, d, dim=1), rtol=0, atol=1e-10 * y.abs().max().item())
