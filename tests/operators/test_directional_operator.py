"""DirectionalOperator batching and devices, Geometry carrying it, and the error when it is missing."""

import pickle

import numpy as np
import pytest
import scipy.sparse as sp
import torch

from zernet.nn.models import build_model
from zernet.nn.reference import MatrixOperator
from zernet.operators import DirectionalOperator, Geometry, build_directional_operator
from zernet.zernike import num_bases

K = num_bases(3)


def _operator(n, seed):
    """A patch operator with random sparse rows and random right-handed frames."""
    rng = np.random.default_rng(seed)
    matrix = sp.random(n * K, n, density=0.4, random_state=seed, format="csr")
    matrix.data = rng.normal(size=matrix.nnz)
    normals = rng.normal(size=(n, 3)) + [0.0, 0.0, 2.5]
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    e1 = np.cross(normals, rng.normal(size=(n, 3)))
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return MatrixOperator(matrix, K, np.stack([e1, np.cross(normals, e1), normals], axis=1))


def test_concatenate_is_block_diagonal():
    ops = [_operator(7, 1), _operator(5, 2)]
    parts = [build_directional_operator(op, 2) for op in ops]
    batch = DirectionalOperator.concatenate(parts)
    assert (batch.n_vertices, batch.order, batch.k) == (12, 2, K)
    # same as building from the concatenated scalar operator (transport never crosses surfaces)
    direct = build_directional_operator(MatrixOperator.concatenate(ops), 2)
    for mine, theirs in zip(batch.phases, direct.phases):
        np.testing.assert_array_equal(mine.toarray(), theirs.toarray())
    torch.manual_seed(0)
    x = [torch.randn(7, 5, 3, dtype=torch.float64), torch.randn(5, 5, 3, dtype=torch.float64)]
    separate = torch.cat([part.apply(xi) for part, xi in zip(parts, x)])
    torch.testing.assert_close(batch.apply(torch.cat(x)), separate, rtol=0, atol=1e-13)
    with pytest.raises(ValueError, match="different"):
        DirectionalOperator.concatenate([parts[0], build_directional_operator(ops[1], 1)])


def test_to_and_pickle_keep_the_values():
    dop = build_directional_operator(_operator(6, 3), 1)
    x = torch.randn(6, 3, 2)
    before = dop.apply(x)
    assert dop.to("cpu") is dop
    assert all(key[2] == torch.device("cpu") for key in dop._torch)
    torch.testing.assert_close(dop.to(torch.device("cpu")).apply(x), before, rtol=0, atol=0)
    clone = pickle.loads(pickle.dumps(dop))
    torch.testing.assert_close(clone.apply(x), before, rtol=0, atol=0)


def test_geometry_builds_moves_and_batches_directional_operators():
    geometries = [Geometry([_operator(7, 4)]), Geometry([_operator(5, 5)])]
    assert geometries[0].directional_order is None
    assert geometries[0].with_directional(None) is geometries[0]
    prepared = [g.with_directional(1) for g in geometries]
    assert prepared[0].directional_order == 1 and geometries[0].directional == []  # a copy, not a change
    assert prepared[0].with_directional(1) is prepared[0]
    moved = prepared[0].to("cpu")
    assert moved.directional_order == 1
    batch = Geometry.concatenate(prepared)
    assert batch.directional_order == 1 and batch.directional[0].n_vertices == 12
    assert batch.directional[0].operator is batch.operators[0]  # built on the batch's scalar operator
    with pytest.raises(ValueError, match="different orders"):
        Geometry.concatenate([prepared[0], geometries[1]])


def test_directional_model_names_the_missing_operators():
    model = build_model("zernet-directional", 3, 4, widths=(5, 6), k=K, angular_resolution=4)
    geometry = Geometry([_operator(9, 6)])
    with pytest.raises(ValueError, match=r"without directional operators of order L=1.*with_directional\(1\)"):
        model(torch.randn(9, 3), geometry)
    with pytest.raises(ValueError, match="order 2"):
        model(torch.randn(9, 3), geometry.with_directional(2))
    assert model(torch.randn(9, 3), geometry.with_directional(model.directional_order)).shape == (9, 4)
