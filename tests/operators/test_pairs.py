"""The compact form of a patch operator (:mod:`zernet.operators.pairs`): conversions, precisions, products."""

import numpy as np
import pytest
import scipy.sparse
import torch

from zernet.operators.pairs import VertexPairs, narrow_index_dtype, pair_product, pair_product_transposed


def random_operator_matrix(n=30, k=4, density=0.2, seed=0, shared=True):
    """An (n k, n) CSR matrix; with ``shared`` each vertex's k rows read the same columns (a patch fit's)."""
    rng = np.random.default_rng(seed)
    pattern = rng.random((n, n)) < density
    dense = np.zeros((n * k, n))
    for p in range(n):
        for j in range(k):
            columns = pattern[p] if shared else pattern[p] & (rng.random(n) < 0.6)
            dense[p * k + j, columns] = rng.standard_normal(columns.sum())
    return scipy.sparse.csr_matrix(dense)


@pytest.mark.parametrize("shared", [True, False])
def test_csr_round_trip_and_products(shared):
    matrix = random_operator_matrix(shared=shared)
    pairs = VertexPairs.from_csr(matrix, 4)
    assert pairs.columns.dtype == np.uint16 and pairs.indptr.dtype == np.int32
    # the pairs are the union of each vertex's rows: a row lacking a column holds a 0 there
    expected_pairs = {(row // 4, col) for row, col in zip(*matrix.nonzero())}
    rows = np.repeat(np.arange(pairs.n_vertices), np.diff(pairs.indptr))
    assert set(zip(rows.tolist(), pairs.columns.tolist())) == expected_pairs
    assert (pairs.to_csr() != matrix).nnz == 0
    x = np.random.default_rng(1).standard_normal((30, 3))
    order = np.array([2, 0, 3, 1])
    y = pair_product([pairs], x, order)
    np.testing.assert_allclose(y, (matrix @ x).reshape(30, 4, 3)[:, order], atol=1e-12)
    g = np.random.default_rng(2).standard_normal((30, 4, 3))
    back = np.empty_like(g)
    back[:, order] = g  # grad of y[:, i] = basis order[i]
    np.testing.assert_allclose(pair_product_transposed([pairs], g, order), matrix.T @ back.reshape(-1, 3), atol=1e-12)


def test_products_of_a_block_diagonal_batch_and_on_several_threads():
    parts = [VertexPairs.from_csr(random_operator_matrix(n=40 + 7 * i, seed=i), 4) for i in range(3)]
    block = scipy.sparse.block_diag([p.to_csr() for p in parts], format="csr")
    n = block.shape[1]
    x = np.random.default_rng(3).standard_normal((n, 5))
    g = np.random.default_rng(4).standard_normal((n, 4, 5))
    order = np.arange(4)
    threads = torch.get_num_threads()
    try:
        for count in (1, 3):  # vertex ranges over threads: the same sums
            torch.set_num_threads(count)
            np.testing.assert_allclose(pair_product(parts, x, order).reshape(-1, 5), block @ x, atol=1e-12)
            np.testing.assert_allclose(pair_product_transposed(parts, g, order), block.T @ g.reshape(-1, 5), atol=1e-12)
    finally:
        torch.set_num_threads(threads)


@pytest.mark.parametrize("precision", ["float32", "float16", "bfloat16"])
def test_stored_precisions_round_to_nearest_and_decode_exactly(precision):
    pairs = VertexPairs.from_csr(random_operator_matrix(), 4)
    stored = pairs.with_precision(precision)
    assert stored.indptr is pairs.indptr and stored.columns is pairs.columns  # indices shared
    expected = torch.from_numpy(pairs.values).to(getattr(torch, precision)).float().numpy()
    np.testing.assert_array_equal(stored.float_values(), expected)  # torch's rounding, decoded without loss
    assert stored.values.itemsize == (4 if precision == "float32" else 2)
    x = np.random.default_rng(5).standard_normal((30, 2)).astype(np.float32)
    np.testing.assert_allclose(
        pair_product([stored], x, np.arange(4)),
        pair_product(
            [VertexPairs(pairs.indptr, pairs.columns, expected.astype(np.float32), "float32")], x, np.arange(4)
        ),
        rtol=1e-6,
        atol=1e-6,
    )


def test_the_backward_scatters_on_any_thread_count_to_the_same_transpose():
    # Each thread scatters into its own buffer: one, two or many work items give the transpose.
    pairs = VertexPairs.from_csr(random_operator_matrix(), 4)
    matrix = pairs.to_csr()
    g = np.random.default_rng(3).standard_normal((pairs.n_vertices, 4, 3))
    expected = matrix.T @ g.reshape(-1, 3)
    for threads in (1, 2, 7):
        torch.set_num_threads(threads)
        try:
            np.testing.assert_allclose(
                pair_product_transposed([pairs, pairs], np.concatenate([g, g]), np.arange(4)),
                np.concatenate([expected, expected]),
                atol=1e-12,
            )
        finally:
            torch.set_num_threads(1)
    assert pairs.nbytes == pairs.indptr.nbytes + pairs.columns.nbytes + pairs.values.nbytes  # nothing else held


def test_narrowest_index_types():
    assert narrow_index_dtype(65535) == np.uint16 and narrow_index_dtype(65536) == np.uint32
    assert narrow_index_dtype(2**33) == np.int64
    with pytest.raises(ValueError, match="precision"):
        VertexPairs(np.zeros(2, np.int32), np.zeros(0, np.uint16), np.zeros((0, 3)), "float8")


def test_pickled_pairs_carry_their_fields_only():
    import pickle

    pairs = VertexPairs.from_csr(random_operator_matrix(), 4).with_precision("bfloat16")
    back = pickle.loads(pickle.dumps(pairs))
    assert back.precision == "bfloat16"
    np.testing.assert_array_equal(back.float_values(), pairs.float_values())
    assert len(pickle.dumps(pairs)) < 1.2 * (pairs.values.nbytes + pairs.columns.nbytes + pairs.indptr.nbytes)
