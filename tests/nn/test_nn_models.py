"""Models: registry, widths, batching of several surfaces, Geometry, state dict."""

import io

import numpy as np
import pytest
import torch

from zernet.nn import MatrixOperator
from zernet.nn.models import MODEL_REGISTRY, MultiScaleZerNet, ZerNet, available_models, build_model, register_model
from zernet.operators import Geometry

pytestmark = pytest.mark.filterwarnings("ignore:Sparse CSR tensor support is in beta")


def geometry(n, seed, scales=1):
    ops = [MatrixOperator.random(n, 21, nnz_per_row=8, seed=seed + 10 * i) for i in range(scales)]
    ring = np.arange(n)
    edges = torch.as_tensor(np.stack([np.r_[ring, (ring + 1) % n], np.r_[(ring + 1) % n, ring]]))
    return Geometry(ops, edges)


def test_registry_and_names():
    names = available_models()
    assert {"zernet", "zernet-multiscale"} <= set(names)
    with pytest.raises(ValueError, match="unknown model"):
        build_model("no-such-model", 3, 2)
    with pytest.raises(ValueError, match="already registered"):
        register_model("zernet")(lambda i, o: None)

    @register_model("test-tiny")
    def tiny(in_channels, out_channels, **options):
        return torch.nn.Linear(in_channels, out_channels)

    assert isinstance(build_model("test-tiny", 3, 2), torch.nn.Linear)
    del MODEL_REGISTRY["test-tiny"]


@pytest.mark.parametrize(
    "task,widths",
    [
        ("correspondence", (64, 128, 256, 512)),
        ("segmentation", (32, 64, 128, 256)),
        ("regression", (128, 256, 512, 800)),
    ],
)
def test_task_widths(task, widths):
    model = build_model("zernet", 3, 8, task=task)
    assert model.widths == widths
    assert [b.convs[0].out_channels for b in model.blocks] == list(widths[:3])
    assert model.hidden.out_features == widths[3] and model.output.out_features == 8


def test_forward_shapes_and_options():
    g = geometry(30, 0, scales=3)
    x = torch.randn(30, 3)
    for name, opts in [
        ("zernet", dict(widths=(8, 16, 12), angular_resolution=4)),
        ("zernet", dict(widths=(8, 12), pooling="continuous", norm="batch", activation="elu")),
        ("zernet-multiscale", dict(widths=(9, 10, 12), angular_resolution=4)),
        ("zernet-multiscale", dict(widths=(9, 10, 12), wiring="sequential", norm="layer")),
    ]:
        out = build_model(name, 3, 5, **opts)(x, g)
        assert out.shape == (30, 5) and torch.isfinite(out).all()
    ms = build_model("zernet-multiscale", 3, 5, widths=(64, 12))
    assert [c.out_channels for c in ms.blocks[0].convs] == [22, 21, 21] and ms.blocks[0].scales == (0, 1, 2)
    with pytest.raises(ValueError):
        build_model("zernet", 3, 5, widths=(8,))
    with pytest.raises(ValueError):
        build_model("zernet-multiscale", 3, 5, widths=(8, 8))(x, geometry(30, 0, scales=1))


@pytest.mark.parametrize("name", ["zernet", "zernet-multiscale"])
def test_batch_of_surfaces_equals_each_alone(name):
    torch.manual_seed(0)
    items = [geometry(n, seed, scales=3) for seed, n in enumerate((17, 30, 23))]
    xs = [torch.randn(g.n_vertices, 3) for g in items]
    model = build_model(name, 3, 4, widths=(8, 16, 12), angular_resolution=8).eval()
    batch = Geometry.concatenate(items)
    assert batch.n_vertices == 70 and batch.num_surfaces == 3
    out = model(torch.cat(xs), batch)
    alone = torch.cat([model(x, g) for x, g in zip(xs, items)])
    torch.testing.assert_close(out, alone, atol=1e-5, rtol=1e-5)


def test_geometry_concatenate_offsets():
    a, b = geometry(5, 0), geometry(7, 1)
    g = Geometry.concatenate([a, b])
    assert g.edge_index.shape == (2, 24)
    assert g.edge_index[:, 10:].min() == 5 and g.edge_index.max() == 11
    assert g.batch.tolist() == [0] * 5 + [1] * 7
    assert g.operators[0].n_vertices == 12
    gg = Geometry.concatenate([g, a])  # a batch of batches keeps surface ids distinct
    assert gg.batch.tolist() == [0] * 5 + [1] * 7 + [2] * 5 and gg.num_surfaces == 3
    moved = g.to("cpu")
    assert moved.batch.device.type == "cpu" and len(moved.operators) == 1
    with pytest.raises(ValueError):
        Geometry.concatenate([a, Geometry(a.operators, None)])
    with pytest.raises(ValueError):
        Geometry.concatenate([])


def test_determinism_and_state_dict_round_trip():
    g = geometry(20, 3)
    x = torch.randn(20, 3)
    torch.manual_seed(5)
    m1 = ZerNet(3, 6, widths=(8, 12, 10), angular_resolution=4).eval()
    torch.manual_seed(5)
    m2 = ZerNet(3, 6, widths=(8, 12, 10), angular_resolution=4).eval()
    torch.testing.assert_close(m1(x, g), m2(x, g), atol=0, rtol=0)
    buf = io.BytesIO()
    torch.save(m1.state_dict(), buf)
    buf.seek(0)
    m3 = ZerNet(3, 6, widths=(8, 12, 10), angular_resolution=4).eval()
    m3.load_state_dict(torch.load(buf, weights_only=True))
    torch.testing.assert_close(m3(x, g), m1(x, g), atol=0, rtol=0)
    ms = MultiScaleZerNet(3, 6, widths=(9, 10))
    ms.reset_parameters()


def test_training_step_reduces_loss():
    torch.manual_seed(0)
    g = geometry(40, 2)
    x = torch.randn(40, 3)
    y = torch.randint(0, 4, (40,))
    model = build_model("zernet", 3, 4, widths=(16, 16, 32), angular_resolution=4, dropout=0.0)
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    losses = []
    for _ in range(15):
        opt.zero_grad()
        loss = torch.nn.functional.cross_entropy(model(x, g), y)
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.7 * losses[0]


@pytest.mark.parametrize("name", ["zernet", "zernet-multiscale"])
def test_input_skip_feeds_the_inputs_to_the_head(name):
    g = geometry(30, 0, scales=3)
    x = torch.randn(30, 3)
    torch.manual_seed(0)
    model = build_model(name, 3, 2, widths=(9, 12), angular_resolution=4, input_skip=True, dropout=0.0).eval()
    assert model.hidden.in_features == 9 + 3
    # The head sees [conv features, x]: zeroing the conv part of the hidden weight leaves a function of x
    # alone, vertex by vertex (no neighbour enters), so shuffling the other vertices' inputs changes nothing.
    with torch.no_grad():
        model.hidden.weight[:, :9] = 0.0
        out = model(x, g)
        shuffled = x.clone()
        shuffled[1:] = x[1:][torch.randperm(29)]
        assert torch.allclose(model(shuffled, g)[0], out[0], atol=1e-6)
        model.hidden.weight[:, 9:] = 0.0  # and without the skip part the output is constant
        assert torch.allclose(model(x, g), model(x, g)[:1].expand(30, 2), atol=1e-6)


@pytest.mark.parametrize("name", ["zernet", "zernet-multiscale"])
def test_input_layer_is_a_per_vertex_map_before_the_first_convolution(name):
    g = geometry(30, 1, scales=3)
    x = torch.randn(30, 5)
    torch.manual_seed(0)
    model = build_model(name, 5, 2, widths=(9, 12), angular_resolution=4, input_width=4, dropout=0.0).eval()
    assert model.input.in_features == 5 and model.input.out_features == 4
    assert all(conv.in_channels == 4 for conv in model.blocks[0].convs)
    # The model is the plain one fed relu(input(x)): copy its later layers into a model without an input layer.
    plain = build_model(name, 4, 2, widths=(9, 12), angular_resolution=4, dropout=0.0).eval()
    plain.load_state_dict({k: v for k, v in model.state_dict().items() if not k.startswith("input.")})
    with torch.no_grad():
        assert torch.allclose(model(x, g), plain(torch.relu(model.input(x)), g), atol=1e-6)
    assert build_model(name, 5, 2, widths=(9, 12), input_width=0).input is None
    with pytest.raises(ValueError, match="input_width"):
        build_model(name, 5, 2, widths=(9, 12), input_width=-1)


@pytest.fixture(scope="module")
def ellipsoid_geometry():
    import trimesh

    from zernet.data.preprocess import mesh_edge_index
    from zernet.geometry import Surface
    from zernet.operators import PatchConfig, build_patch_operator

    mesh = trimesh.creation.icosphere(subdivisions=2)
    surface = Surface(
        vertices=np.asarray(mesh.vertices) * [1.3, 1.0, 0.8], faces=np.asarray(mesh.faces), name="ellipsoid"
    )
    operator = build_patch_operator(surface, PatchConfig(r0=0.6, n_samples=1500, patch_size=30, n_max=5, seed=0))
    return Geometry([operator], mesh_edge_index(surface))


@pytest.mark.parametrize("name", ["zernet", "zernet-multiscale", "zernet-directional", "feastnet", "paper-zernet"])
def test_every_model_trains_under_bfloat16_autocast(name, ellipsoid_geometry):
    """train.precision bfloat16: convolutions stay float32, linear layers run in bfloat16, and the output
    stays within bfloat16 rounding of the float32 model's."""
    geometry = ellipsoid_geometry
    if name == "zernet-multiscale":
        geometry = Geometry(geometry.operators * 3, geometry.edge_index)
    torch.manual_seed(0)
    model = build_model(name, 3, 5, widths=(8, 16, 16, 32))
    geometry = geometry.with_directional(model.directional_order)  # built before the network, as the data do
    model.eval()  # no dropout: the two passes must see the same network
    x = torch.randn(geometry.operators[0].n_vertices, 3)
    reference = model(x, geometry)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        mixed = model(x, geometry)
    assert torch.isfinite(mixed).all()
    error = (mixed.float() - reference).norm() / reference.norm()
    assert error < 0.05, f"{name}: bfloat16 output {error:.3f} away from float32"
    mixed.float().square().mean().backward()
    grads = [p.grad for p in model.parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)


def test_convolutions_run_in_float32_under_autocast(ellipsoid_geometry):
    from zernet.nn import ZernikeConv

    operator = ellipsoid_geometry.operators[0]
    conv = ZernikeConv(4, 6, angular_resolution=4)
    x = torch.randn(operator.n_vertices, 4)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        inside = conv(x.bfloat16(), operator)  # e.g. the output of a bfloat16 linear layer
    assert inside.dtype == torch.float32
    torch.testing.assert_close(inside, conv(x.bfloat16().float(), operator), rtol=0, atol=0)
