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

from zernet.geometry import Surface
from zernet.nn.conv import ZernikeConv
from zernet.nn.models import FeaStNet, PaperZerNet, PaperZernikeConv, build_model
from zernet.nn.reference import MatrixOperator
from zernet.operators import Geometry, PatchConfig, build_patch_operator
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
def turned():
    surface = _surface(2, 1.3)
    rotation = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    surface = Surface(vertices=surface.vertices @ rotation.T, faces=surface.faces, name="ico2-turned")
    return surface, _geometry(surface)


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


def _toy_operator(n_vertices=7, n_samples=40, patch=9, n_max=2, ridge=0.01, subtract_center=False, seed=0):
    """A hand-made operator: random patches and interpolation, plus the matching precomputed matrix.

    It has what the paper's layer reads (``patch_sample_index``, ``patch_basis``, ``interpolation``,
    ``config``) and what ZernikeConv reads (``apply``, ``k``), the latter from the closed-form ridge fit.
    """
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
    dense = interpolation.toarray()
    matrix = np.zeros((n_vertices * k, n_vertices))
    for p in range(n_vertices):
        valid = index[p] >= 0
        b, s = basis[p][valid], dense[index[p][valid]]
        if subtract_center:
            s = s - np.eye(n_vertices)[p]
        matrix[p * k : (p + 1) * k] = np.linalg.solve(b.T @ b + ridge * np.eye(k), b.T @ s)
    precomputed = MatrixOperator(matrix, k)
    config = SimpleNamespace(ridge=ridge, subtract_center=subtract_center)
    return SimpleNamespace(
        k=k,
        n_max=n_max,
        n_vertices=n_vertices,
        lam=ridge,
        patch_sample_index=index,
        patch_basis=basis,
        interpolation=interpolation,
        config=config,
        apply=precomputed.apply,
        matrix=precomputed.matrix,
    )


@pytest.mark.parametrize("subtract_center", [False, True])
def test_paper_fit_is_the_ridge_least_squares_solution(subtract_center):
    op = _toy_operator(subtract_center=subtract_center)
    conv = PaperZernikeConv(3, 4, k=op.k).double()
    x = torch.randn(op.n_vertices, 3, dtype=torch.float64)
    torch.testing.assert_close(conv.fit(x, op), op.apply(x), rtol=1e-10, atol=1e-12)
    override = PaperZernikeConv(3, 4, k=op.k, ridge=0.5).double()
    assert not torch.allclose(override.fit(x, op), op.apply(x))


def test_paper_conv_is_max_over_rotated_kernel_copies():
    op = _toy_operator()
    torch.manual_seed(0)
    conv = PaperZernikeConv(3, 4, k=op.k, angular_resolution=5).double()
    x = torch.randn(op.n_vertices, 3, dtype=torch.float64)
    coeffs = conv.fit(x, op)
    responses = torch.stack(
        [
            torch.einsum("nki,kio->no", coeffs, rotate_coefficients(conv.weight, 2 * math.pi * a / 5, dim=0))
            for a in range(5)
        ]
    )
    torch.testing.assert_close(conv(x, op), responses.amax(0) + conv.bias)


@pytest.mark.parametrize("s", [1, 2, 4, 7, 16])
def test_paper_conv_equals_zernikeconv_max_pooling_on_toy_operator(s):
    op = _toy_operator(n_max=5, patch=30, subtract_center=True)
    torch.manual_seed(s)
    ours = ZernikeConv(3, 6, k=op.k, angular_resolution=s, pooling="max")
    paper = PaperZernikeConv(3, 6, k=op.k, angular_resolution=s, ridge=None)
    paper.load_state_dict(ours.state_dict())
    x = torch.randn(op.n_vertices, 3)
    # float64: the same map up to rounding
    torch.testing.assert_close(paper.double()(x.double(), op), ours.double()(x.double(), op), rtol=1e-9, atol=1e-10)
    # float32: the per-call solve loses about cond(BᵀB + λI) ~ 5e3 times the float32 epsilon
    expected = ours.float()(x, op)
    torch.testing.assert_close(paper.float()(x, op), expected, rtol=0, atol=1e-3 * expected.abs().max().item())


def test_paper_zernet_is_zernet_with_the_paper_layer():
    op = _toy_operator(n_max=3, patch=20)
    geometry = Geometry(operators=[op])
    options = dict(widths=(8, 12, 16), n_max=3, angular_resolution=4)
    torch.manual_seed(5)
    zernet = build_model("zernet", 3, 4, **options).eval()
    after_zernet = torch.rand(1)
    torch.manual_seed(5)
    paper = build_model("paper-zernet", 3, 4, **options).eval()
    assert torch.equal(torch.rand(1), after_zernet)  # same RNG consumption: same dropout draws in training
    assert isinstance(paper, PaperZerNet)
    assert all(isinstance(conv, PaperZernikeConv) for block in paper.blocks for conv in block.convs)
    assert paper.state_dict().keys() == zernet.state_dict().keys()
    for key, value in zernet.state_dict().items():
        assert torch.equal(paper.state_dict()[key], value), key
    x = torch.randn(op.n_vertices, 3, dtype=torch.float64)
    torch.testing.assert_close(paper.double()(x, geometry), zernet.double()(x, geometry), rtol=1e-9, atol=1e-10)
    with pytest.raises(ValueError, match="pooling"):
        build_model("paper-zernet", 3, 4, pooling="continuous")


@pytest.mark.parametrize("fixture", ["sphere", "sphere_centered"])
def test_paper_fit_equals_precomputed_patch_operator(fixture, request):
    """On a real surface, the per-layer fit reproduces zernet's once-per-surface sparse operator."""
    surface, geometry = request.getfixturevalue(fixture)
    operator = geometry.operators[0]
    conv = PaperZernikeConv(3, 2, k=operator.k).double()
    x = torch.as_tensor(surface.vertices) + 0.1 * torch.randn(surface.n_vertices, 3, dtype=torch.float64)
    torch.testing.assert_close(conv.fit(x, operator), operator.apply(x), rtol=1e-7, atol=1e-9)


@pytest.mark.parametrize("s", [1, 4, 16])
def test_paper_conv_equals_zernikeconv_max_pooling(sphere, s):
    surface, geometry = sphere
    operator = geometry.operators[0]
    torch.manual_seed(2)
    ours = ZernikeConv(3, 5, k=operator.k, angular_resolution=s, pooling="max")
    paper = PaperZernikeConv(3, 5, k=operator.k, angular_resolution=s)
    paper.load_state_dict(ours.state_dict())
    x = _features(surface)
    expected = ours(x, operator)
    torch.testing.assert_close(paper(x, operator), expected, rtol=0, atol=1e-3 * expected.abs().max().item())
    x = x.double()
    torch.testing.assert_close(paper.double()(x, operator), ours.double()(x, operator), rtol=1e-7, atol=1e-9)


def test_paper_zernet_model_forward_backward_and_batch(sphere, turned):
    # A batch of two surfaces with the same ridge λ (a concatenated operator carries one λ; see the
    # PaperZernikeConv docstring): the mesh and a turned copy of it, so the patch fits are the same.
    (s1, g1), (s2, g2) = sphere, turned
    assert g1.operators[0].lam == pytest.approx(g2.operators[0].lam, rel=1e-9)
    model = build_model("paper-zernet", 3, 4, n_max=g1.operators[0].n_max, angular_resolution=4, **SMALL)
    assert [c.out_channels for b in model.blocks for c in b.convs] == [8, 12]
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
        options = dict(n_max=geometry.operators[0].n_max, angular_resolution=4) if name == "paper-zernet" else {}
        model = build_model(name, 3, 3, **options, **SMALL)
        optimiser = torch.optim.Adam(model.parameters(), lr=1e-2)
        loss = torch.nn.functional.cross_entropy(model(x, geometry), target)
        loss.backward()
        optimiser.step()
        return loss.item(), [p.detach().clone() for p in model.parameters()]

    (loss_a, params_a), (loss_b, params_b) = one_step(), one_step()
    assert loss_a == loss_b
    for a, b in zip(params_a, params_b):
        assert torch.equal(a, b)
