"""PyTorch Geometric interop (zernet.pyg): the transform's operators are zernet's, a PyG batch runs the models
as the shapes one by one, and the attachments survive an InMemoryDataset on disk and a DataLoader."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from meshes import cylinder_mesh, icosphere, random_sphere_points
from torch_geometric.data import Batch, Data, InMemoryDataset
from torch_geometric.loader import DataLoader

from zernet.data.features import compute_features
from zernet.geometry import Surface, normalize_area
from zernet.nn.models import build_model
from zernet.operators import Geometry, PatchConfig, PatchOperator, build_patch_operator
from zernet.pyg import PairOperator, ZernetOperators, geometry_from_pyg, operator_keys

CONFIGS = [PatchConfig(r0=0.6, n_samples=1200, n_max=5), PatchConfig(r0=0.9, n_samples=1200, n_max=5)]


@pytest.fixture(autouse=True)
def _one_thread(one_torch_thread):
    """Tiny tensors on a shared machine: one thread."""


def _sphere(seed: int = 0) -> Surface:
    return icosphere(2, noise=0.03, seed=seed, name=f"sphere{seed}")


def _cylinder() -> Surface:
    vertices, faces = cylinder_mesh(0.8, 2.5, 18, 7)
    return Surface(vertices, faces, name="cylinder")


def _data(surface: Surface) -> Data:
    """A PyG mesh as data sets hold it: float32 positions, faces (3, F)."""
    return Data(pos=torch.tensor(surface.vertices, dtype=torch.float32), face=torch.tensor(surface.faces.T))


def _as_read(surface: Surface) -> Surface:
    """The surface as the transform reads it from the float32 ``pos``."""
    return Surface(np.asarray(surface.vertices, np.float32).astype(np.float64), surface.faces, name=surface.name)


def _same_matrix(a, b) -> None:
    """The same operator: the same entries, values equal up to one float16 rounding step. Reading a cache file
    fits its patches again, and the BLAS of another thread count can round the last bit of a float64 fit
    differently, which moves a few float16 values by one step."""
    a, b = a.tocsr(), b.tocsr()
    a.sort_indices(), b.sort_indices()
    assert a.shape == b.shape and np.array_equal(a.indptr, b.indptr) and np.array_equal(a.indices, b.indices)
    assert np.all(np.abs(a.data - b.data) <= 2.0**-10 * np.abs(b.data) + 1e-7)


def test_transform_operators_equal_build_patch_operator(tmp_path):
    surface = _sphere()
    data = ZernetOperators(CONFIGS, cache_dir=tmp_path / "cache")(_data(surface))
    geometry = geometry_from_pyg(data)
    assert len(geometry.operators) == 2 and geometry.batch is None
    for config, operator in zip(CONFIGS, geometry.operators):
        reference = build_patch_operator(_as_read(surface), config, cache_dir=tmp_path / "cache")  # float32
        _same_matrix(operator.matrix, reference.matrix)
        np.testing.assert_array_equal(operator.frames, reference.frames)
        x = torch.randn(surface.n_vertices, 2, dtype=torch.float64)
        order = tuple(np.random.default_rng(0).permutation(operator.k))
        assert torch.equal(operator.apply(x, basis_order=order), reference.apply(x, basis_order=order))
    np.testing.assert_array_equal(data.x.numpy(), compute_features(_as_read(surface), "xyz"))

    # no cache: the float64 fit, stored in the cache's precision; with an area: the scaled surface's operator
    plain = geometry_from_pyg(ZernetOperators(CONFIGS[0])(_data(surface))).operators[0]
    assert plain.value.dtype == torch.float16  # PatchConfig.precision
    _same_matrix(plain.matrix, build_patch_operator(_as_read(surface), CONFIGS[0]).as_cached().matrix)
    scaled = ZernetOperators(CONFIGS[0], area=20.0, features="xyz+normals")(_data(surface))
    normalised, _ = normalize_area(_as_read(surface), 20.0)
    _same_matrix(
        geometry_from_pyg(scaled).operators[0].matrix,
        build_patch_operator(normalised, CONFIGS[0]).as_cached().matrix,
    )
    assert scaled.x.shape == (surface.n_vertices, 6) and torch.equal(scaled.pos, _data(surface).pos)


def test_point_cloud_and_pair_operator_round_trip(tmp_path):
    points = random_sphere_points(150, seed=1)
    data = ZernetOperators(CONFIGS[0], cache_dir=tmp_path)(Data(pos=torch.tensor(points, dtype=torch.float32)))
    cloud = Surface(np.asarray(points, np.float32).astype(np.float64), name="cloud")
    _same_matrix(geometry_from_pyg(data).operators[0].matrix, build_patch_operator(cloud, CONFIGS[0], tmp_path).matrix)
    assert geometry_from_pyg(data).edge_index is None

    # pairs given out of order are sorted; a batch's matrix is the surfaces' block diagonal
    reference = build_patch_operator(_sphere(), CONFIGS[0])
    pairs = PairOperator.from_operator(reference)
    shuffle = torch.randperm(pairs.index.shape[1], generator=torch.Generator().manual_seed(0))
    shuffled = PairOperator(pairs.index[:, shuffle], pairs.value[shuffle], pairs.n_vertices, pairs.frames_tensor)
    cached = reference.as_cached()  # the values in the cache's precision, as the pairs hold them
    _same_matrix(shuffled.matrix, cached.matrix)
    both = PairOperator.concatenate([pairs, shuffled])
    _same_matrix(both.matrix, PatchOperator.concatenate([cached, cached]).matrix)
    with pytest.raises(AttributeError, match="patch samples"):
        _ = pairs.patch_sample_index


MODELS = {
    "zernet": dict(widths=(6, 8, 10), angular_resolution=4, norm="layer"),
    "zernet-multiscale": dict(widths=(6, 10), n_scales=2, angular_resolution=4),
    "zernet-directional": dict(widths=(4, 6, 8), angular_resolution=4),
    "feastnet": dict(widths=(6, 8, 10)),
}


@pytest.fixture(scope="module")
def two_shapes(tmp_path_factory):
    """A sphere and a cylinder through the transform (two scales), and the operator cache they were built in."""
    cache = tmp_path_factory.mktemp("pyg") / "cache"
    surfaces = [_sphere(1), _cylinder()]
    transform = ZernetOperators(CONFIGS, cache_dir=cache)
    return surfaces, [transform(_data(s)) for s in surfaces], cache


@pytest.mark.parametrize("name", sorted(MODELS))
def test_batch_of_two_gives_the_shapes_one_by_one(two_shapes, name):
    surfaces, items, cache = two_shapes
    batch = Batch.from_data_list(items)
    torch.manual_seed(0)
    model = build_model(name, 3, 5, **MODELS[name]).double().eval()
    order = model.directional_order
    with torch.no_grad():
        together = model(batch.x.double(), geometry_from_pyg(batch, order))
        alone = [model(d.x.double(), geometry_from_pyg(d, order)) for d in items]
        # zernet's own geometry of the same surfaces (operators from the same cache) answers the same
        native = Geometry(
            [build_patch_operator(_as_read(surfaces[0]), c, cache) for c in CONFIGS],
            geometry_from_pyg(items[0]).edge_index,
        ).with_directional(order)
        first = model(items[0].x.double(), native)
    assert together.shape == (batch.num_nodes, 5)
    torch.testing.assert_close(together, torch.cat(alone), rtol=0, atol=1e-10)
    torch.testing.assert_close(first, alone[0], rtol=0, atol=1e-10)
    geometry = geometry_from_pyg(batch)
    assert torch.equal(geometry.batch, batch.batch) and geometry.num_surfaces == 2
    concatenated = Geometry.concatenate([geometry_from_pyg(d) for d in items])
    for ours, theirs in zip(geometry.operators, concatenated.operators):
        _same_matrix(ours.matrix, theirs.matrix)
    edges = lambda e: sorted(map(tuple, e.T.tolist()))  # noqa: E731  (the same edges, in another order)
    assert edges(geometry.edge_index) == edges(concatenated.edge_index)


class _Shapes(InMemoryDataset):
    """Three small meshes generated in ``process``, saved under ``root/processed``."""

    def __init__(self, root, pre_transform=None):
        super().__init__(str(root), pre_transform=pre_transform)
        self.load(self.processed_paths[0])

    @property
    def processed_file_names(self):
        return ["shapes.pt"]

    def process(self):
        data_list = [_data(s) for s in (_sphere(0), _cylinder(), _sphere(2))]
        for data in data_list:
            data.y = torch.arange(data.num_nodes)
        self.save([self.pre_transform(d) for d in data_list], self.processed_paths[0])


def test_in_memory_dataset_and_data_loader(tmp_path):
    transform = ZernetOperators(CONFIGS[0], cache_dir=tmp_path / "cache")
    built = _Shapes(tmp_path / "shapes", pre_transform=transform)
    reloaded = _Shapes(tmp_path / "shapes", pre_transform=transform)  # read back from disk, not processed
    assert len(reloaded) == 3
    for i in range(3):
        for key in (*operator_keys(0), "x", "pos", "face"):
            assert torch.equal(reloaded[i][key], built[i][key]), key

    torch.manual_seed(0)
    model = build_model("zernet", 3, 4, widths=(6, 8), angular_resolution=4, dropout=0.0).eval()
    loader = DataLoader(reloaded, batch_size=2, shuffle=False)
    batches = list(loader)
    assert [b.num_graphs for b in batches] == [2, 1]
    with torch.no_grad():
        out = torch.cat([model(b.x, geometry_from_pyg(b)) for b in batches])
        alone = torch.cat([model(d.x, geometry_from_pyg(d)) for d in reloaded])
    torch.testing.assert_close(out, alone, rtol=1e-5, atol=1e-6)

    # a training step on a batch: node targets are positions within each graph
    batch = batches[0]
    model.train()
    target = torch.arange(batch.num_nodes) - batch.ptr[batch.batch]
    assert torch.equal(target, batch.y)
    loss = torch.nn.functional.cross_entropy(model(batch.x, geometry_from_pyg(batch)), target % 4)
    loss.backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in model.parameters())
