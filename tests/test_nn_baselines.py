"""Baselines of issue 5: FeaStNet (PyG FeaStConv) and the paper's per-layer least-squares ZerNet."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import scipy.sparse
import torch
import trimesh
from torch_geometric.nn import FeaStConv

from zernet.nn.baselines import FeaStNet, PaperZernikeConv, PaperZerNet
from zernet.nn.geometry import Geometry
from zernet.nn.models import build_model
from zernet.patches import PatchConfig, build_patch_operator
from zernet.surface import Surface
from zernet.zernike import num_bases, rotate_coefficients, zernike_basis

SMALL = dict(widths=(8, 12, 16))


def _edge_index(faces: np.ndarray) -> torch.Tensor:
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    edges = np.unique(np.sort(edges, axis=1), axis=0)
    return torch.as_tensor(np.concatenate([edges, edges[:, ::-1]]).T.copy(), dtype=torch.long)


def _surface(subdivisions: int, stretch: float) -> Surface:
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions)
    vertices = np.asarray(mesh.vertices, dtype=np.float64) * np.array([stretch, 1.0, 0.8])
    return Surface(vertices=vertices, faces=np.asarray(mesh.faces, dtype=np.int64), name=f"ico{subdivisions}")


def _geometry(surface: Surface, **config) -> Geometry:
    options = dict(r0=0.6, n_samples=1500, patch_size=30, n_max=3, seed=0)
    options.update(config)
    operator = build_patch_operator(surface, PatchConfig(**options))
    return Geometry(operators=[operator], edge_index=_edge_index(surface.faces))


@pytest.fixture(scope="module")
def sphere():
    surface = _surface(2, 1.3)
    return surface, _geometry(surface)


@pytest.fixture(scope="module")
def sphere_centered():
    surface = _surface(2, 1.3)
    return surface, _geometry(surface, subtract_center=True, ridge=1e-2)


@pytest.fixture(scope="module")
def other():
    surface = _surface(1, 0.9)
    return surface, _geometry(surface)


def _features(surface: Surface) -> torch.Tensor:
    return torch.as_tensor(surface.vertices, dtype=torch.float32)


# ------------------------------------------------------------------------------------------- FeaStNet


def test_feastnet_is_registered_and_built_on_pyg_feastconv():
    model = build_model("feastnet", 3, 7)
    assert isinstance(model, FeaStNet)
    convs = [m for m in model.modules() if isinstance(m, FeaStConv)]
    assert [c.out_channels for c in convs] == [64, 128, 256]
    assert all(c.heads == 8 and c.add_self_loops for c in convs)
    assert model.input.out_features == 16
    assert model.hidden.out_features == 512 and model.output.out_features == 7


def test_feastnet_forward_backward(sphere):
    surface, geometry = sphere
    torch.manual_seed(0)
    model = FeaStNet(3, 5, **SMALL)
    x = _features(surface)
    out = model(x, geometry)
    assert out.shape == (surface.n_vertices, 5)
    assert torch.isfinite(out).all()
    out.square().mean().backward()
    for name, parameter in model.named_parameters():
        assert parameter.grad is not None and torch.isfinite(parameter.grad).all(), name
    assert any(p.grad.abs().sum() > 0 for p in model.convs[0].parameters())


def test_feastnet_without_input_layer_and_feastnet_paper_widths(sphere):
    surface, geometry = sphere
    model = FeaStNet(3, 4, widths=(32, 64, 128, 256), input_width=None)
    assert model.input is None and model.convs[0].in_channels == 3
    assert model(_features(surface), geometry).shape == (surface.n_vertices, 4)


def test_feastnet_needs_edges(sphere):
    surface, geometry = sphere
    model = FeaStNet(3, 2, **SMALL)
    with pytest.raises(ValueError, match="edge_index"):
        model(_features(surface), Geometry(operators=geometry.operators))


def test_feastnet_batch_of_two_surfaces_equals_separate_runs(sphere, other):
    (s1, g1), (s2, g2) = sphere, other
    torch.manual_seed(1)
    model = FeaStNet(3, 6, **SMALL).eval()
    batched = Geometry.concatenate([g1, g2])
    x = torch.cat([_features(s1), _features(s2)])
    out = model(x, batched)
    assert out.shape == (s1.n_vertices + s2.n_vertices, 6)
    torch.testing.assert_close(out[: s1.n_vertices], model(_features(s1), g1), rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(out[s1.n_vertices :], model(_features(s2), g2), rtol=1e-4, atol=1e-5)


# ------------------------------------------------------------------------------- paper formulation


def _toy_operator(n_vertices=7, n_samples=40, patch=9, n_max=2, ridge=0.01, seed=0):
    """A hand-made operator (random patches and interpolation) with only what the paper's layer reads."""
    rng = np.random.default_rng(seed)
    k = num_bases(n_max)
    index = rng.integers(0, n_samples, size=(n_vertices, patch))
    index[0, 3:] = -1  # a patch with fewer samples than bases: the ridge keeps it well posed
    r, theta = rng.uniform(0, 1, index.shape), rng.uniform(-math.pi, math.pi, index.shape)
    basis = zernike_basis(r, theta, n_max) * (index >= 0)[..., None]
    rows = np.repeat(np.arange(n_samples), 3)
    cols = rng.integers(0, n_vertices, size=3 * n_samples)
    weights = rng.dirichlet(np.ones(3), size=n_samples).ravel()
    interpolation = scipy.sparse.csr_matrix((weights, (rows, cols)), shape=(n_samples, n_vertices))
    config = SimpleNamespace(ridge=ridge, subtract_center=False)
    return SimpleNamespace(k=k, n_max=n_max, patch_sample_index=index, patch_basis=basis,
                           interpolation=interpolation, config=config)


def test_paper_conv_fit_and_rotated_max_against_direct_formula():
    op = _toy_operator()
    torch.manual_seed(0)
    conv = PaperZernikeConv(3, 4, k=op.k, rotations=5).double()
    x = torch.randn(7, 3, dtype=torch.float64)
    # fit: per vertex, ridge least squares on the valid samples
    samples = op.interpolation @ x.numpy()
    expected = []
    for p in range(7):
        valid = op.patch_sample_index[p] >= 0
        b, f = op.patch_basis[p][valid], samples[op.patch_sample_index[p][valid]]
        expected.append(np.linalg.solve(b.T @ b + 0.01 * np.eye(op.k), b.T @ f))
    coeffs = conv.fit(x, op)
    np.testing.assert_allclose(coeffs.detach().numpy(), np.stack(expected), rtol=1e-10, atol=1e-12)
    # rotated kernel copies at 2πa/s, max over a
    responses = torch.stack([
        torch.einsum("nki,kio->no", coeffs, rotate_coefficients(conv.weight, 2 * math.pi * a / 5, dim=0))
        for a in range(5)
    ])
    torch.testing.assert_close(conv(x, op), responses.amax(0) + conv.bias)


@pytest.mark.parametrize("fixture", ["sphere", "sphere_centered"])
def test_paper_fit_equals_precomputed_operator(fixture, request):
    """The per-layer ridge fit reproduces zernet's once-per-surface sparse operator (same λ convention)."""
    surface, geometry = request.getfixturevalue(fixture)
    operator = geometry.operators[0]
    conv = PaperZernikeConv(3, 2, k=operator.k).double()
    x = torch.as_tensor(surface.vertices) + 0.1 * torch.randn(surface.n_vertices, 3, dtype=torch.float64)
    torch.testing.assert_close(conv.fit(x, operator), operator.apply(x), rtol=1e-7, atol=1e-9)


@pytest.mark.parametrize("rotations", [1, 4, 7])
def test_paper_conv_equals_zernikeconv_max_pooling(sphere, rotations):
    from zernet.nn.conv import ZernikeConv

    surface, geometry = sphere
    operator = geometry.operators[0]
    torch.manual_seed(2)
    ours = ZernikeConv(3, 5, k=operator.k, rotations=rotations, pooling="max")
    paper = PaperZernikeConv(3, 5, k=operator.k, rotations=rotations)
    with torch.no_grad():
        paper.weight.copy_(ours.weight)
        paper.bias.copy_(ours.bias)
    x = _features(surface)
    torch.testing.assert_close(paper(x, operator), ours(x, operator), rtol=1e-4, atol=1e-5)


def test_paper_zernet_model_forward_backward_and_batch(sphere, other):
    (s1, g1), (s2, g2) = sphere, other
    model = build_model("paper-zernet", 3, 4, k=g1.operators[0].k, **SMALL)
    assert isinstance(model, PaperZerNet)
    assert [c.out_channels for c in model.convs] == [8, 12]
    out = model(_features(s1), g1)
    assert out.shape == (s1.n_vertices, 4)
    out.square().mean().backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in model.parameters())
    model.eval()
    batched = model(torch.cat([_features(s1), _features(s2)]), Geometry.concatenate([g1, g2]))
    torch.testing.assert_close(batched[: s1.n_vertices], model(_features(s1), g1), rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(batched[s1.n_vertices :], model(_features(s2), g2), rtol=1e-4, atol=1e-5)


# ------------------------------------------------------------------------------------ determinism


@pytest.mark.parametrize("name", ["feastnet", "paper-zernet"])
def test_same_seed_same_training_step(name, sphere):
    surface, geometry = sphere
    x = _features(surface)
    target = torch.arange(surface.n_vertices) % 3

    def one_step():
        torch.manual_seed(123)
        model = build_model(name, 3, 3, k=geometry.operators[0].k, **SMALL) if name == "paper-zernet" \
            else build_model(name, 3, 3, **SMALL)
        optimiser = torch.optim.Adam(model.parameters(), lr=1e-2)
        loss = torch.nn.functional.cross_entropy(model(x, geometry), target)
        loss.backward()
        optimiser.step()
        return loss.item(), [p.detach().clone() for p in model.parameters()]

    (loss_a, params_a), (loss_b, params_b) = one_step(), one_step()
    assert loss_a == loss_b
    for a, b in zip(params_a, params_b):
        assert torch.equal(a, b)
