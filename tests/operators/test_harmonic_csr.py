"""The directional operator's harmonic matrix and its transpose (zernet/operators/harmonic_csr.py), and
its pairs and transport angles kept beside the cached patch operator, so that a data set streamed from its
cache gives what one held in memory gives."""

from functools import partial

import numpy as np
import pytest
import scipy.sparse as sp
import torch
from meshes import icosphere, patch_like_operator, random_frames

from zernet.data.preprocess import ShapeSource, build_dataset
from zernet.fourier import fourier_dim
from zernet.inference.batch import Batch
from zernet.nn.models import build_model
from zernet.nn.reference import MatrixOperator
from zernet.operators import CacheWarning, PatchConfig, build_directional_operator, build_patch_operator
from zernet.operators.directional import transport_cache_path
from zernet.zernike import num_bases

K = num_bases(3)
CONFIG = PatchConfig(r0=0.6, n_samples=800, patch_size=20, n_max=3, seed=0)


_patch_like_operator = partial(patch_like_operator, K)


def _scattered_operator(n=12, seed=1):
    """Rows of a vertex read different vertices (not the block layout)."""
    matrix = sp.random(n * K, n, density=0.3, random_state=seed, format="csr")
    matrix.data = np.random.default_rng(seed).normal(size=matrix.nnz)
    return MatrixOperator(matrix, K, random_frames(np.random.default_rng(seed), n))


def _reference_harmonic_matrix(dop, harmonics):
    """The matrix of apply_harmonic assembled entry by entry from A and the phase matrices ``[C_ℓ; S_ℓ]``."""
    a = dop.operator.matrix.tocsr()
    a.sort_indices()
    phases = [m.tocsr() for m in dop.phases]
    d, n = fourier_dim(dop.order), dop.n_vertices
    indptr, indices, data = [0], [], []
    for p in range(n):
        for x in harmonics:
            j, r = divmod(x, d)
            row = p * dop.k + j
            columns = a.indices[a.indptr[row] : a.indptr[row + 1]]
            if r == 0:
                for q, value in zip(columns, a.data[a.indptr[row] : a.indptr[row + 1]]):
                    indices.append(q * d)
                    data.append(value)
            else:
                ell = (r + 1) // 2
                c_row, s_row = phases[ell - 1][2 * row], phases[ell - 1][2 * row + 1]
                for q, c, s in zip(columns, c_row.data, s_row.data):
                    indices += [q * d + 2 * ell - 1, q * d + 2 * ell]
                    data += [c, -s] if r % 2 == 1 else [s, c]
            indptr.append(len(indices))
    return np.asarray(indptr), np.asarray(indices), np.asarray(data)


@pytest.mark.parametrize("make_operator", [_patch_like_operator, _scattered_operator])
@pytest.mark.parametrize("order", [1, 2])
def test_harmonic_matrix_equals_the_reference_construction(make_operator, order):
    dop = build_directional_operator(make_operator(), order)
    d = fourier_dim(order)
    for harmonics in (range(K * d), (0, 7, 6, 13, 2 * d + 1), (d, 0)):
        matrix = dop.harmonic_matrix(harmonics)
        indptr, indices, data = _reference_harmonic_matrix(dop, list(harmonics))
        np.testing.assert_array_equal(matrix.indptr, indptr)
        np.testing.assert_array_equal(matrix.indices, indices)
        np.testing.assert_array_equal(matrix.data, data)  # bitwise: the same products


@pytest.mark.parametrize("make_operator", [_patch_like_operator, _scattered_operator])
def test_torch_matrices_are_the_matrix_and_its_transpose(make_operator):
    dop = build_directional_operator(make_operator(), 2)
    harmonics = (0, 1, 4, 5, 12, 23)
    expected = dop.harmonic_matrix(harmonics)
    transpose = expected.T.tocsr()
    matrix64, transpose64 = dop.torch_matrices(harmonics, torch.float64, "cpu")
    for mine, theirs in ((matrix64, expected), (transpose64, transpose)):
        assert tuple(mine.shape) == theirs.shape
        np.testing.assert_array_equal(mine.crow_indices().numpy(), theirs.indptr)
        np.testing.assert_array_equal(mine.col_indices().numpy(), theirs.indices)
        np.testing.assert_array_equal(mine.values().numpy(), theirs.data)
    matrix32, transpose32 = dop.torch_matrices(harmonics, torch.float32, "cpu")
    np.testing.assert_array_equal(matrix32.values().numpy(), expected.data.astype(np.float32))
    np.testing.assert_array_equal(transpose32.values().numpy(), transpose.data.astype(np.float32))


def test_pairs_that_miss_an_entry_are_refused():
    op = _patch_like_operator()
    dop = build_directional_operator(op, 1)
    dop.pairs, dop.angles = dop.pairs[1:], dop.angles[1:]
    with pytest.raises(ValueError, match="do not cover"):
        dop.harmonic_matrix([1])


def test_transport_angles_are_cached_beside_the_operator(tmp_path, monkeypatch):
    surface = icosphere(2, noise=0.02)
    operator = build_patch_operator(surface, CONFIG, cache_dir=tmp_path)
    built = build_directional_operator(operator, 1)
    path = transport_cache_path(operator.cache_file)
    assert path.is_file() and path.parent == tmp_path
    # read back, not recomputed: an operator loaded from the cache finds them without computing angles
    monkeypatch.setattr("zernet.operators.directional.transport_angles", _must_not_run)
    loaded = build_directional_operator(build_patch_operator(surface, CONFIG, cache_dir=tmp_path), 2)
    np.testing.assert_array_equal(loaded.pairs, built.pairs)
    np.testing.assert_array_equal(loaded.angles, built.angles)
    assert loaded.pairs.dtype == np.int64
    monkeypatch.undo()
    # a damaged file is reported and rebuilt, never misread
    path.write_bytes(b"not an npz file")
    with pytest.warns(CacheWarning, match="transport"):
        rebuilt = build_directional_operator(build_patch_operator(surface, CONFIG, cache_dir=tmp_path), 1)
    np.testing.assert_array_equal(rebuilt.angles, built.angles)
    build_directional_operator(build_patch_operator(surface, CONFIG, cache_dir=tmp_path), 1)  # rewritten: quiet


def _must_not_run(*args, **kwargs):
    raise AssertionError("transport angles recomputed although they are cached")


def _sphere_source(seed):
    surface = icosphere(2, noise=0.02, seed=seed, name=f"sphere{seed}")
    return surface, np.arange(surface.n_vertices) % 3


def test_streamed_dataset_gives_the_in_memory_directional_loss(tmp_path):
    sources = [ShapeSource(f"s{i}", partial(_sphere_source, i), key=f"sphere-{i}") for i in range(2)]
    common = dict(
        patch_configs=[CONFIG],
        cache_dir=tmp_path,
        target_area=None,
        task="classification",
        num_classes=3,
        split_names={"train": ["s0", "s1"]},
        workers=0,
        progress=False,
    )
    held = build_dataset(sources, in_memory=True, **common)
    streamed = build_dataset(sources, in_memory=False, **common)
    assert held.in_memory and not streamed.in_memory
    torch.manual_seed(0)
    model = build_model("zernet-directional", 3, 3, widths=(4, 4), angular_resolution=4, k=K).double().eval()
    order = model.directional_order
    losses = []
    for dataset in (held, streamed, streamed):  # the second streamed pass reads the cached transport angles
        batch = Batch([dataset[0], dataset[1]], torch.device("cpu"), directional_order=order)
        output = model(batch.features.double(), batch.geometry)
        losses.append(torch.nn.functional.cross_entropy(output, batch.target))
    assert transport_cache_path(streamed[0].geometry.operators[0].cache_file).is_file()
    torch.testing.assert_close(losses[1], losses[0], rtol=0, atol=0)
    torch.testing.assert_close(losses[2], losses[0], rtol=0, atol=0)
