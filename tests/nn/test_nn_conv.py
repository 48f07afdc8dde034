"""ZernikeConv: harmonic form vs rotated kernels, gradients, invariances, flat-disk convolution, state."""

import io
import math

import numpy as np
import pytest
import torch
from meshes import icosphere

from zernet.nn import MatrixOperator, RotatedKernelConv, ZernikeConv, harmonic_contraction, harmonic_plan
from zernet.nn.reference import rotated_kernel_responses
from zernet.operators import PatchConfig, build_patch_operator
from zernet.zernike import num_bases, rotate_coefficients, zernike_basis

pytestmark = pytest.mark.filterwarnings("ignore:Sparse CSR tensor support is in beta")


class RotatedFrames:
    """An operator whose every vertex's reference direction is turned: F_p -> rotate_coefficients(F_p, δ_p)."""

    def __init__(self, op, delta):
        self.op, self.delta, self.k, self.n_max = op, delta, op.k, op.n_max

    def apply(self, x):
        F = self.op.apply(x)
        return rotate_coefficients(F, self.delta.to(F.dtype)[:, None], dim=1)


def setup(N=30, C_in=4, seed=0, dtype=torch.float32, k=21):
    torch.manual_seed(seed)
    op = MatrixOperator.random(N, k, nnz_per_row=8, seed=seed)
    x = torch.randn(N, C_in, dtype=dtype)
    return op, x


@pytest.mark.parametrize(
    "pooling,shape", [("max", (30, 6)), ("mean", (30, 6)), ("continuous", (30, 6)), ("none", (30, 8, 6))]
)
def test_shapes(pooling, shape):
    op, x = setup()
    conv = ZernikeConv(4, 6, angular_resolution=8, pooling=pooling)
    assert conv(x, op).shape == shape
    assert conv.weight.shape == (21, 4, 6)


@pytest.mark.parametrize("s", [1, 2, 4, 8, 16])
def test_harmonic_form_equals_rotated_kernels(s):
    op, x = setup(C_in=5)
    conv = ZernikeConv(5, 7, angular_resolution=s, pooling="none")
    ref = RotatedKernelConv(5, 7, angular_resolution=s, pooling="none")
    ref.load_state_dict(conv.state_dict())
    with torch.no_grad():
        conv.bias.normal_()
        ref.bias.copy_(conv.bias)
    out, expected = conv(x, op), ref(x, op)
    assert out.shape == (30, s, 7)
    scale = expected.abs().max().item()
    torch.testing.assert_close(out, expected, atol=4e-7 * scale, rtol=0)
    for mode in ("max", "mean"):
        conv.pooling = ref.pooling = mode
        torch.testing.assert_close(conv(x, op), ref(x, op), atol=4e-7 * scale, rtol=0)


def test_unfolded_harmonics_sample_the_rotated_kernel():
    op, x = setup()
    conv = ZernikeConv(4, 3)
    H = conv.harmonics(x, op)  # true polynomial, degree n_max
    assert H.shape == (11, 30, 3)
    phis = torch.tensor([0.3, -1.7, 2.9])
    F = op.apply(x)
    for phi in phis:
        direct = F.reshape(30, -1) @ rotate_coefficients(conv.weight, phi, dim=0).reshape(-1, 3)
        m = torch.arange(1, 6, dtype=torch.float32)
        trig = torch.cat([torch.ones(1), torch.stack([torch.cos(m * phi), torch.sin(m * phi)], 1).reshape(-1)])
        torch.testing.assert_close(torch.einsum("h,hnc->nc", trig, H), direct, atol=2e-5, rtol=0)


def test_plan_folding_costs():
    # rows feeding two outputs cost twice: s=1 and s=2 cost one unrotated contraction
    def cost(s):
        p = harmonic_plan(5, s)
        return sum((b - a) * (2 if (f > 0 and p.has_sin[f]) else 1) for f, (a, b) in enumerate(p.groups))

    assert cost(1) == 21 and cost(2) == 21 and cost(4) == 33 and cost(16) == 39 and cost(None) == 39
    assert harmonic_plan(5, 1).identity and harmonic_plan(5, 16).degree == 5 and harmonic_plan(5, 4).degree == 2


@pytest.mark.parametrize("pooling,s", [("max", 4), ("mean", 4), ("none", 3), ("continuous", 4), ("max", 1)])
def test_gradcheck_float64(pooling, s):
    torch.manual_seed(1)
    op = MatrixOperator.random(6, 6, nnz_per_row=4, seed=1)  # n_max = 2
    x = torch.randn(6, 2, dtype=torch.float64, requires_grad=True)
    conv = ZernikeConv(2, 3, n_max=2, angular_resolution=s, pooling=pooling).double()
    w0 = conv.weight.detach().clone().requires_grad_()
    b0 = conv.bias.detach().clone().normal_().requires_grad_()
    assert torch.autograd.gradcheck(lambda x, w, b: ZernikeConv.forward(_with(conv, w, b), x, op), (x, w0, b0))


def _with(conv, w, b):
    """The same layer with weight/bias replaced by given tensors (functional call for gradcheck)."""
    clone = ZernikeConv(conv.in_channels, conv.out_channels, conv.n_max, conv.angular_resolution, conv.pooling)
    del clone.weight, clone.bias
    clone.weight, clone.bias = w, b
    return clone


def test_gradients_match_reference():
    op, x = setup(C_in=3)
    x.requires_grad_()
    conv = ZernikeConv(3, 4, angular_resolution=8, pooling="none")
    ref = RotatedKernelConv(3, 4, angular_resolution=8, pooling="none")
    ref.load_state_dict(conv.state_dict())
    g = torch.randn(30, 8, 4)
    gx, gw = torch.autograd.grad((conv(x, op) * g).sum(), (x, conv.weight))
    rx, rw = torch.autograd.grad((ref(x, op) * g).sum(), (x, ref.weight))
    torch.testing.assert_close(gx, rx, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(gw, rw, atol=1e-5, rtol=1e-5)


def test_continuous_pooling_is_independent_of_reference_directions():
    op, x = setup(N=40, C_in=4, seed=3)
    conv = ZernikeConv(4, 8, pooling="continuous")
    delta = torch.rand(40, dtype=torch.float64) * 2 * math.pi
    out = conv(x, op)
    turned = conv(x, RotatedFrames(op, delta))
    torch.testing.assert_close(turned, out, atol=2e-5 * out.abs().max().item(), rtol=0)
    # the continuous max is at least the best of 64 sampled rotations
    ref = rotated_kernel_responses(op.apply(x), conv.weight, 64).amax(1) + conv.bias
    assert (out >= ref - 1e-5).all()
    # ... and discrete max pooling is not invariant to arbitrary angles
    conv.pooling, conv.angular_resolution = "max", 4
    assert (conv(x, op) - conv(x, RotatedFrames(op, delta))).abs().max() > 1e-3


@pytest.mark.parametrize("s", [2, 4, 8])
def test_discrete_pooling_invariant_to_multiples_of_2pi_over_s(s):
    op, x = setup(N=25, C_in=3, seed=4)
    conv = ZernikeConv(3, 5, angular_resolution=s, pooling="max")
    delta = torch.randint(0, s, (25,), dtype=torch.float64) * (2 * math.pi / s)
    out = conv(x, op)
    torch.testing.assert_close(conv(x, RotatedFrames(op, delta)), out, atol=1e-5 * out.abs().max().item(), rtol=0)


def _disk_quadrature(n_r=30, n_t=96):
    xg, wg = np.polynomial.legendre.leggauss(n_r)
    r = 0.5 * (xg + 1)
    t = 2 * np.pi * np.arange(n_t) / n_t
    R, T = np.meshgrid(r, t, indexing="ij")
    W = np.outer(0.5 * wg * r, np.full(n_t, 2 * np.pi / n_t))
    return R.ravel(), T.ravel(), W.ravel()


def test_agrees_with_direct_convolution_on_a_flat_disk():
    """Response = ∫ f(r, θ) g(r, θ + φ_a) dA over the unit disk, by quadrature, for analytic f and g."""
    n_max = 5
    r, t, w = _disk_quadrature()
    Z = zernike_basis(r, t, n_max)
    X, Y = r * np.cos(t), r * np.sin(t)
    f = lambda X, Y: 1.0 + X**3 - 2 * X * Y + 0.5 * Y**5 - X**2 * Y**2  # noqa: E731  degree 5: in the span
    g = lambda X, Y: np.exp(0.7 * X) * np.cos(1.3 * Y + 0.2) + Y  # noqa: E731  not band-limited
    a_f = Z.T @ (w * f(X, Y))
    a_g = Z.T @ (w * g(X, Y))
    s = 4
    conv = ZernikeConv(1, 1, n_max=n_max, angular_resolution=s, pooling="none", bias=False).double()
    with torch.no_grad():
        conv.weight.copy_(torch.as_tensor(a_g).view(-1, 1, 1))
    op = MatrixOperator(a_f[:, None], num_bases(n_max))  # one vertex whose patch coefficients are a_f
    out = conv(torch.ones(1, 1, dtype=torch.float64), op)[0, :, 0].detach().numpy()
    for a in range(s):
        phi = 2 * np.pi * a / s
        Xr, Yr = r * np.cos(t + phi), r * np.sin(t + phi)  # kernel turned: g(r, θ + φ)
        integral = np.sum(w * f(X, Y) * g(Xr, Yr))
        assert out[a] == pytest.approx(integral, abs=1e-10)
    conv.angular_resolution = 1
    assert conv(torch.ones(1, 1, dtype=torch.float64), op).item() == pytest.approx(
        np.sum(w * f(X, Y) * g(X, Y)), abs=1e-10
    )


def test_determinism_state_dict_and_repr():
    op, x = setup()
    torch.manual_seed(7)
    a = ZernikeConv(4, 6, angular_resolution=4)
    torch.manual_seed(7)
    b = ZernikeConv(4, 6, angular_resolution=4)
    torch.testing.assert_close(a(x, op), b(x, op), atol=0, rtol=0)
    buf = io.BytesIO()
    torch.save(a.state_dict(), buf)
    buf.seek(0)
    c = ZernikeConv(4, 6, angular_resolution=4)
    c.load_state_dict(torch.load(buf, weights_only=True))
    torch.testing.assert_close(c(x, op), a(x, op), atol=0, rtol=0)
    assert set(a.state_dict()) == {"weight", "bias"}
    assert repr(a) == "ZernikeConv(4, 6, n_max=5, k=21, angular_resolution=4, pooling='max', bias=True)"
    bound = math.sqrt(6 / (21 * 4))
    assert a.weight.abs().max() <= bound and torch.all(a.bias == 0)


def test_options_and_errors():
    conv = ZernikeConv(2, 3, k=10, bias=False)
    assert conv.n_max == 3 and conv.bias is None
    with pytest.raises(ValueError):
        ZernikeConv(2, 3, k=11)
    with pytest.raises(ValueError):
        ZernikeConv(2, 3, pooling="median")
    with pytest.raises(ValueError):
        ZernikeConv(2, 3, angular_resolution=0)
    op, x = setup(C_in=2)
    with pytest.raises(ValueError, match="k=10"):
        conv(x, op)
    with pytest.raises(ValueError):
        ZernikeConv(3, 3)(x, op)
    with pytest.raises(ValueError):
        harmonic_contraction(torch.zeros(3, 21, 2), torch.zeros(21, 3, 1), harmonic_plan(5, 4))


def test_real_patch_operator_on_small_mesh():
    surface = icosphere(2)
    op = build_patch_operator(surface, PatchConfig(r0=0.6, n_samples=1500, patch_size=30, n_max=3))
    x = torch.as_tensor(surface.vertices, dtype=torch.float32)
    conv = ZernikeConv(3, 4, n_max=3, angular_resolution=8, pooling="continuous")
    out = conv(x, op)
    assert out.shape == (surface.n_vertices, 4) and torch.isfinite(out).all()
    delta = torch.rand(surface.n_vertices, dtype=torch.float64) * 2 * math.pi
    torch.testing.assert_close(conv(x, RotatedFrames(op, delta)), out, atol=1e-5 * out.abs().max().item(), rtol=0)
    conv.pooling = "none"
    ref = rotated_kernel_responses(op.apply(x), conv.weight, 8) + conv.bias
    torch.testing.assert_close(conv(x, op), ref, atol=1e-5 * ref.abs().max().item(), rtol=0)


class PlainOperator:
    """Only ``apply(x)``, ``k`` and ``n_max``: an operator that cannot return coefficients in another order."""

    def __init__(self, op):
        self.op, self.k, self.n_max, self.n_vertices = op, op.k, op.n_max, op.n_vertices

    def apply(self, x):
        return self.op.apply(x)


def test_operator_basis_order_is_the_order_the_forward_asks_for():
    # What data pipelines prepare ahead (zernet.inference.batch.model_basis_orders) must be exactly what the
    # forward pass requests, or the preparation is wasted and the reordering is paid in the forward again.
    op, x = setup()
    asked = []

    class Recording(MatrixOperator):
        def apply(self, x, basis_order=None):
            asked.append(basis_order)
            return super().apply(x, basis_order=basis_order)

    recording = Recording(op.matrix, op.k)
    for conv in (
        ZernikeConv(4, 3, angular_resolution=16),
        ZernikeConv(4, 3, angular_resolution=4, pooling="continuous"),
        ZernikeConv(4, 3, angular_resolution=1),
        ZernikeConv(4, 3, angular_resolution=8, pooling="mean"),
        RotatedKernelConv(4, 3, angular_resolution=8),
    ):
        asked.clear()
        conv(x, recording)
        assert asked == [conv.operator_basis_order()]
    assert ZernikeConv(4, 3, angular_resolution=16).operator_basis_order() == harmonic_plan(5, 16).perm
    assert ZernikeConv(4, 3, angular_resolution=1).operator_basis_order() is None
    assert RotatedKernelConv(4, 3, angular_resolution=8).operator_basis_order() is None


@pytest.mark.parametrize("s,pooling", [(4, "max"), (8, "max"), (16, "max"), (5, "none"), (4, "continuous")])
def test_coefficients_in_plan_order_equal_the_gathered_ones(s, pooling):
    # ZernikeConv asks an operator that can for F grouped by frequency; the result and the gradients must
    # be those of gathering F itself.
    op, x = setup(dtype=torch.float64)
    conv = ZernikeConv(4, 3, angular_resolution=s, pooling=pooling).double()
    assert op.accepts_basis_order and not conv._plan().identity
    x.requires_grad_()
    outs, grads = [], []
    for operator in (op, PlainOperator(op)):
        out = conv(x, operator)
        outs.append(out)
        grads.append(torch.autograd.grad(out.sum(), (x, conv.weight)))
    torch.testing.assert_close(outs[0], outs[1])
    for a, b in zip(*grads):
        torch.testing.assert_close(a, b)
