"""Angular pooling and the harmonic-form helpers."""

import math

import pytest
import torch

from zernet.nn.pooling import (
    angular_pool,
    continuous_max,
    discrete_max,
    equispaced_angles,
    evaluate_harmonics,
    harmonic_degree,
    harmonic_mean,
    trig_basis,
)


def test_trig_basis_layout():
    phi = torch.tensor([0.0, 0.4], dtype=torch.float64)
    T = trig_basis(phi, 3)
    assert T.shape == (2, 7)
    expected = torch.tensor(
        [1, math.cos(0.4), math.sin(0.4), math.cos(0.8), math.sin(0.8), math.cos(1.2), math.sin(1.2)]
    )
    torch.testing.assert_close(T[1], expected.double())
    torch.testing.assert_close(T[0], torch.tensor([1.0, 1, 0, 1, 0, 1, 0]).double())


def test_evaluate_and_mean():
    torch.manual_seed(0)
    H = torch.randn(9, 5, 3, dtype=torch.float64)
    angles = equispaced_angles(12, torch.float64)
    S = evaluate_harmonics(H, angles)
    assert S.shape == (12, 5, 3)
    torch.testing.assert_close(S.mean(0), harmonic_mean(H))
    with pytest.raises(ValueError):
        harmonic_degree(torch.zeros(4, 2))


def test_discrete_max_value_and_gradient_match_autograd_max():
    torch.manual_seed(1)
    H = torch.randn(11, 40, 6, dtype=torch.float64, requires_grad=True)
    for s in (1, 3, 8, 16):
        out = discrete_max(H, s)
        ref = evaluate_harmonics(H, equispaced_angles(s, torch.float64)).amax(0)
        torch.testing.assert_close(out, ref)
        g = torch.randn_like(out)
        (ga,) = torch.autograd.grad((out * g).sum(), H)
        (gb,) = torch.autograd.grad((ref * g).sum(), H)
        torch.testing.assert_close(ga, gb)
    assert torch.autograd.gradcheck(lambda h: discrete_max(h, 5), (H[:, :3, :2].detach().clone().requires_grad_(),))


def test_discrete_max_in_chunks_and_with_ties(monkeypatch):
    import zernet.nn.pooling as pooling

    torch.manual_seed(3)
    s = 8
    H = torch.randn(9, 50, 7, dtype=torch.float64, requires_grad=True)
    whole = discrete_max(H, s)
    monkeypatch.setattr(pooling, "_POOL_CHUNK_ELEMENTS", 3 * s)  # 3 columns per chunk, a ragged last one
    torch.testing.assert_close(discrete_max(H, s), whole)
    g = torch.randn(50, 7, dtype=torch.float64)
    (chunked,) = torch.autograd.grad((discrete_max(H, s) * g).sum(), H)
    (ref,) = torch.autograd.grad((evaluate_harmonics(H, equispaced_angles(s, torch.float64)).amax(0) * g).sum(), H)
    torch.testing.assert_close(chunked, ref)

    # Only A_0: all s angles tie. The value is A_0 and the gradient is that of one angle (a subgradient):
    # g on A_0, and g times cos/sin of a single sample angle on the other harmonics.
    flat = torch.zeros(9, 4, 1, dtype=torch.float64)
    flat[0] = torch.arange(4.0).view(4, 1)
    flat.requires_grad_()
    out = discrete_max(flat, s)
    torch.testing.assert_close(out, flat[0].detach())
    (grad,) = torch.autograd.grad(out.sum(), flat)
    T = trig_basis(equispaced_angles(s, torch.float64), 4)
    for column in grad[:, :, 0].t():
        assert any(torch.allclose(column, row) for row in T)


def test_continuous_max_is_the_maximum_over_the_circle():
    torch.manual_seed(2)
    for D in (1, 2, 5, 7):
        H = torch.randn(2 * D + 1, 600, dtype=torch.float64)
        value, phi = continuous_max(H, return_angle=True)
        dense = evaluate_harmonics(H, equispaced_angles(4096, torch.float64)).amax(0)
        assert (value >= dense - 1e-12).all()
        assert (value - dense).abs().max() < 1e-4 * dense.abs().max()  # dense grid's own error
        torch.testing.assert_close(evaluate_harmonics(H[:, :1], phi[:1]).reshape(-1), value[:1])
    const = torch.zeros(1, 4)
    torch.testing.assert_close(continuous_max(const), const[0])


def test_continuous_max_gradient_and_shift_invariance():
    torch.manual_seed(3)
    H = torch.randn(7, 4, 2, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(continuous_max, (H,))
    # shifting each polynomial by an arbitrary angle leaves its maximum unchanged
    D = 3
    Hs = H.detach().float()
    shift = torch.rand(4, 2) * 2 * math.pi
    rotated = Hs.clone()
    for m in range(1, D + 1):
        c, s = torch.cos(m * shift), torch.sin(m * shift)
        A, B = Hs[2 * m - 1], Hs[2 * m]
        rotated[2 * m - 1], rotated[2 * m] = A * c + B * s, -A * s + B * c  # p(φ) -> p(φ + shift)
    torch.testing.assert_close(continuous_max(rotated), continuous_max(Hs), atol=1e-5, rtol=1e-5)


def test_angular_pool_modes():
    x = torch.randn(5, 4, 3)
    torch.testing.assert_close(angular_pool(x, "max"), x.amax(1))
    torch.testing.assert_close(angular_pool(x, "mean"), x.mean(1))
    assert angular_pool(x, "none") is x
    with pytest.raises(ValueError):
        angular_pool(x, "continuous")
