"""The patch operator: analytic coefficients, invariances, autograd, batching and the on-disk cache."""

import os

import numpy as np
import pytest
import torch
import trimesh

from zernet.geometry import Surface, compute_polar, sample_surface
from zernet.operators import (
    CacheWarning,
    PatchConfig,
    PatchOperator,
    assemble_operator,
    build_patch_operator,
    cache_key,
)
from zernet.zernike import num_bases, rotate_coefficients, zernike_basis


def grid_mesh(n, spacing):
    """Square triangulated grid in the z = 0 plane centred at the origin; (V, F)."""
    x, y = np.meshgrid((np.arange(n) - (n - 1) / 2) * spacing, (np.arange(n) - (n - 1) / 2) * spacing)
    vertices = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    index = np.arange(n * n).reshape(n, n)
    a, b, c, d = index[:-1, :-1].ravel(), index[:-1, 1:].ravel(), index[1:, :-1].ravel(), index[1:, 1:].ravel()
    return vertices, np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])


def bumpy_sphere(subdivisions=2, seed=0):
    """An icosphere with random radial noise (no exact distance ties between vertices)."""
    mesh = trimesh.creation.icosphere(subdivisions, radius=4.0)
    rng = np.random.default_rng(seed)
    return Surface(mesh.vertices * (1 + 0.03 * rng.standard_normal((len(mesh.vertices), 1))), mesh.faces)


@pytest.fixture(scope="module")
def plane():
    vertices, faces = grid_mesh(41, 0.25)  # 10 × 10 square
    return Surface(vertices, faces)


def frame_angle(frames, p):
    """Angle of e1 from the x axis for a vertex of the z = +1-normal plane."""
    return np.arctan2(frames[p, 0, 1], frames[p, 0, 0])


# ---------------------------------------------------------------------- analytic coefficients
def test_plane_reproduces_zernike_coefficients():
    vertices, faces = grid_mesh(25, 0.2)  # 4.8 × 4.8: fine enough for degree-5 fields to interpolate well
    plane = Surface(vertices, faces)
    r0 = 2.0
    # ~400 samples per disk, all kept, so that patches cover the whole unit disk.
    config = PatchConfig(r0=r0, n_samples=800, patch_size=1000, ridge=1e-8)
    op = build_patch_operator(plane, config)
    center = int(np.argmin(np.linalg.norm(plane.vertices, axis=1)))
    assert np.allclose(op.frames[center, 2], [0, 0, 1])
    alpha = frame_angle(op.frames, center)
    x, y = (plane.vertices[:, :2] - plane.vertices[center, :2]).T / r0
    for j in (0, 2, 4, 7, 12, 20):
        field = zernike_basis(np.hypot(x, y), np.arctan2(y, x), 5)[:, j]
        coeffs = op.apply(torch.from_numpy(field))[center].numpy()
        # In the vertex's frame θ_frame = θ_global - α, so f(r, θ_frame + α): coefficients rotated by α.
        expected = rotate_coefficients(np.eye(21)[j], alpha)
        # Piecewise-linear interpolation of the degree-n field (grid step r0 / 10) leaks a few per cent
        # into lower even modes; the coefficient itself is recovered to ~1 %.
        assert abs(coeffs @ expected - 1.0) < 0.03, (j, coeffs @ expected)
        assert np.abs(coeffs - expected).max() < 0.08, (j, coeffs, expected)


def test_linear_fields_exact_and_constant_field(plane):
    r0 = 1.5
    # All samples of the disk (patch_size large), so the fit is well conditioned and the ridge negligible.
    op = build_patch_operator(plane, PatchConfig(r0=r0, n_samples=2000, patch_size=500, ridge=1e-10))
    rng = np.random.default_rng(0)
    a, b, c = rng.standard_normal(3)
    field = a + b * plane.vertices[:, 0] + c * plane.vertices[:, 1]
    coeffs = op.apply(torch.from_numpy(field)).numpy()
    interior = np.flatnonzero(np.abs(plane.vertices[:, :2]).max(axis=1) < 5 - r0)
    # f = a' + r0 r (b' cos θ + c' sin θ) in each frame: only j = 0, 1, 2 and known values.
    alpha = np.arctan2(op.frames[:, 0, 1], op.frames[:, 0, 0])
    z0 = 1 / np.sqrt(np.pi)
    z1 = 2 / np.sqrt(np.pi)  # Z_1^{±1} = 2 r cos/sin / √π
    expected = np.zeros_like(coeffs)
    expected[:, 0] = field / z0
    # b x + c y with x = r0 r cos(θ + α): cos part (b cos α + c sin α), sin part (-b sin α + c cos α).
    expected[:, 2] = r0 * (b * np.cos(alpha) + c * np.sin(alpha)) / z1  # j=2 is (n=1, m=+1) cos
    expected[:, 1] = r0 * (-b * np.sin(alpha) + c * np.cos(alpha)) / z1  # j=1 is (n=1, m=-1) sin
    assert np.abs(coeffs[interior] - expected[interior]).max() < 1e-5
    # A constant field has only the piston coefficient, everywhere (boundary included).
    constant = op.apply(torch.ones(op.n_vertices, dtype=torch.float64)).numpy()
    assert np.allclose(constant[interior, 0], np.sqrt(np.pi), rtol=1e-6)
    assert np.abs(constant[interior, 1:]).max() < 1e-6
    # Truncated boundary patches: the ridge shrinks what the samples cannot see, never inflates it.
    assert np.all(constant[:, 0] <= np.sqrt(np.pi) * (1 + 1e-6))


def test_subtract_center_removes_constants(plane):
    op = build_patch_operator(plane, PatchConfig(r0=1.5, n_samples=4000, subtract_center=True))
    x = torch.from_numpy(3.0 + 0.0 * plane.vertices[:, 0])
    assert torch.abs(op.apply(x)).max() < 1e-9
    plain = build_patch_operator(plane, PatchConfig(r0=1.5, n_samples=4000))
    f = torch.from_numpy(np.sin(plane.vertices[:, 0]) + plane.vertices[:, 1] ** 2)
    # subtract_center fits f - f(p): the difference to the plain fit is f(p) times the fit of 1.
    difference = plain.apply(f) - op.apply(f)
    ones = plain.apply(torch.ones_like(f))
    assert torch.allclose(difference, f[:, None] * ones, atol=1e-10)


# ---------------------------------------------------------------------- invariances
def test_rotating_frames_rotates_coefficients():
    surface = bumpy_sphere()
    config = PatchConfig(r0=1.5, n_samples=3000)
    samples = sample_surface(surface, config.n_samples, seed=config.seed)
    polar = compute_polar(surface, samples, config.r0)
    op = assemble_operator(
        polar.center, polar.sample, polar.radius, polar.angle, polar.frames, samples.interpolation, config
    )
    delta = np.random.default_rng(0).uniform(-np.pi, np.pi, surface.n_vertices)
    # Turning e1 by +δ_p lowers every angle at p by δ_p.
    turned = assemble_operator(
        polar.center,
        polar.sample,
        polar.radius,
        polar.angle - delta[polar.center],
        polar.frames,
        samples.interpolation,
        config,
    )
    field = torch.from_numpy(np.random.default_rng(1).standard_normal((surface.n_vertices, 3)))
    a, b = op.apply(field).numpy(), turned.apply(field).numpy()
    assert np.allclose(b, rotate_coefficients(a, delta[:, None], dim=1), atol=1e-9)


def test_reindexing_vertices_permutes_operator():
    surface = bumpy_sphere(seed=2)
    config = PatchConfig(r0=1.5, n_samples=3000)
    op = build_patch_operator(surface, config)
    perm = np.random.default_rng(0).permutation(surface.n_vertices)  # new vertex i = old vertex perm[i]
    inverse = np.argsort(perm)
    moved = Surface(surface.vertices[perm], inverse[surface.faces])  # same faces, same order, same samples
    op2 = build_patch_operator(moved, config)
    x = np.random.default_rng(1).standard_normal((surface.n_vertices, 2))
    y = op.apply(torch.from_numpy(x)).numpy()
    y2 = op2.apply(torch.from_numpy(x[perm])).numpy()
    assert np.allclose(y2, y[perm], atol=1e-9)


def test_rigid_motion_leaves_coefficients_unchanged():
    surface = bumpy_sphere(seed=3)
    config = PatchConfig(r0=1.5, n_samples=3000)
    op = build_patch_operator(surface, config)
    rotation = trimesh.transformations.random_rotation_matrix(np.random.default_rng(5).random(3))[:3, :3]
    moved = Surface(surface.vertices @ rotation.T + [10.0, -3.0, 2.0], surface.faces)
    op2 = build_patch_operator(moved, config)
    x = torch.from_numpy(np.random.default_rng(2).standard_normal((surface.n_vertices, 4)))
    assert torch.allclose(op.apply(x), op2.apply(x), atol=1e-7)


# ---------------------------------------------------------------------- apply and autograd
def test_apply_matches_dense_and_follows_dtype():
    op = build_patch_operator(bumpy_sphere(1), PatchConfig(r0=2.0, n_samples=800))
    dense = op.matrix.toarray()
    x = np.random.default_rng(0).standard_normal((op.n_vertices, 5))
    for dtype, tol in ((torch.float64, 1e-12), (torch.float32, 1e-4)):
        y = op.apply(torch.from_numpy(x).to(dtype))
        assert y.dtype == dtype and y.shape == (op.n_vertices, op.k, 5)
        assert np.allclose(y.double().numpy(), (dense @ x).reshape(op.n_vertices, op.k, 5), atol=tol)
    single = op.apply(torch.from_numpy(x[:, 0]))
    assert single.shape == (op.n_vertices, op.k)
    assert torch.allclose(single, op.apply(torch.from_numpy(x))[..., 0])
    with pytest.raises(ValueError):
        op.apply(torch.zeros(op.n_vertices + 1, 2))


def test_gradcheck_and_backward_is_transpose():
    op = build_patch_operator(bumpy_sphere(1), PatchConfig(r0=2.0, n_samples=600, n_max=3))
    x = torch.randn(op.n_vertices, 2, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(op.apply, (x,), eps=1e-6, atol=1e-8, fast_mode=True)
    g = torch.randn(op.n_vertices, op.k, 2, dtype=torch.float64)
    (grad,) = torch.autograd.grad(op.apply(x), x, g)
    assert np.allclose(grad.numpy(), op.matrix.T @ g.reshape(-1, 2).numpy())


def test_a_batch_backward_is_the_transpose_and_holds_nothing_more():
    # The backward scatters from the pairs as stored (no column order is built or kept), for a batch of
    # several surfaces too.
    op = build_patch_operator(bumpy_sphere(1), PatchConfig(r0=2.0, n_samples=600, n_max=3))
    held = op.prepared_nbytes
    batch = PatchOperator.concatenate([op, op])
    x = torch.randn(2 * op.n_vertices, 2, dtype=torch.float64, requires_grad=True)
    g = torch.randn(2 * op.n_vertices, op.k, 2, dtype=torch.float64)
    (grad,) = torch.autograd.grad(batch.apply(x), x, g)
    assert np.allclose(grad.numpy(), batch.matrix.T @ g.reshape(-1, 2).numpy())
    assert op.prepared_nbytes == held == op.pairs.nbytes


def test_apply_in_another_basis_order_is_the_gathered_apply():
    op = build_patch_operator(bumpy_sphere(1), PatchConfig(r0=2.0, n_samples=600, n_max=3))
    order = tuple(np.random.default_rng(1).permutation(op.k).tolist())
    x = torch.randn(op.n_vertices, 3, dtype=torch.float64, requires_grad=True)
    g = torch.randn(op.n_vertices, op.k, 3, dtype=torch.float64)
    reordered = op.apply(x, basis_order=order)
    torch.testing.assert_close(reordered, op.apply(x)[:, list(order)])
    (grad,) = torch.autograd.grad(reordered, x, g)
    (expected,) = torch.autograd.grad(op.apply(x)[:, list(order)], x, g)
    torch.testing.assert_close(grad, expected)
    torch.testing.assert_close(op.apply(x, basis_order=range(op.k)), op.apply(x))  # identity: the plain matrix
    assert op.to("cpu") is op and op.apply(x, basis_order=order).shape == (op.n_vertices, op.k, 3)
    for bad in ((0,) * op.k, tuple(range(op.k + 1))):
        with pytest.raises(ValueError, match="permutation"):
            op.apply(x, basis_order=bad)


def test_to_on_the_cpu_prepares_nothing_and_checks_the_basis_orders():
    # A data pipeline prepares the operator ahead (PatchOperator.to); on the CPU the products read the pairs
    # as they are, and a basis order needs nothing prepared (it picks values), but a bad one is an error.
    op = build_patch_operator(bumpy_sphere(1), PatchConfig(r0=2.0, n_samples=600, n_max=3))
    order = tuple(np.random.default_rng(2).permutation(op.k).tolist())
    other_k = tuple(range(op.k + 5))[::-1]  # an order for another n_max (multi-scale models): skipped
    assert op.to("cpu", basis_orders=[order, other_k]) is op
    assert op.prepared_nbytes == op.pairs.nbytes
    x = torch.randn(op.n_vertices, 2)
    torch.testing.assert_close(op.apply(x, basis_order=order), op.apply(x)[:, list(order)])
    with pytest.raises(ValueError, match="permutation"):
        op.to("cpu", basis_orders=[(0,) * op.k])


# ---------------------------------------------------------------------- truncated patches, components
def test_boundary_sparse_and_isolated_vertices_are_finite():
    vertices, faces = grid_mesh(11, 0.5)
    vertices = np.concatenate([vertices, [[50.0, 50.0, 0.0]]])  # a vertex no face uses
    surface = Surface(vertices, faces)
    op = build_patch_operator(surface, PatchConfig(r0=0.8, n_samples=150, ridge=1e-3))
    counts = (op.patch_sample_index >= 0).sum(axis=1)
    assert counts[:-1].min() < op.k  # some patches have fewer samples than coefficients
    assert counts[-1] == 0
    x = torch.from_numpy(np.random.default_rng(0).standard_normal((surface.n_vertices, 3)))
    y = op.apply(x)
    assert torch.isfinite(y).all()
    assert torch.all(y[-1] == 0)  # no samples: zero rows
    # Ridge keeps the fit bounded: coefficients of a unit-bounded field stay moderate everywhere.
    assert torch.abs(op.apply(torch.ones(surface.n_vertices, dtype=torch.float64))).max() < 20


def test_two_components_and_concatenate():
    a = bumpy_sphere(1, seed=0)
    vertices, faces = grid_mesh(9, 0.5)
    both = Surface(np.concatenate([a.vertices, vertices + [20, 0, 0]]), np.concatenate([a.faces, faces + a.n_vertices]))
    config = PatchConfig(r0=1.5, n_samples=1500)
    op = build_patch_operator(both, config)
    coo = op.matrix.tocoo()
    row_vertex = coo.row // op.k
    assert np.all((row_vertex < a.n_vertices) == (coo.col < a.n_vertices))  # no coupling across components

    # Different patch widths exercise the padding of the patch arrays.
    narrow = PatchConfig(r0=1.5, n_samples=1500, patch_size=30)
    ops = [build_patch_operator(a, config), build_patch_operator(Surface(vertices, faces), narrow)]
    assert ops[0].patch_sample_index.shape[1] != ops[1].patch_sample_index.shape[1]
    joined = PatchOperator.concatenate(ops)
    x = torch.randn(joined.n_vertices, 3, dtype=torch.float64)
    expected = torch.cat([ops[0].apply(x[: a.n_vertices]), ops[1].apply(x[a.n_vertices :])])
    assert torch.allclose(joined.apply(x), expected)
    assert joined.patch_sample_index.shape[0] == joined.n_vertices
    assert joined.patch_basis.shape == joined.patch_sample_index.shape + (joined.k,)
    assert joined.interpolation.shape == (sum(o.interpolation.shape[0] for o in ops), joined.n_vertices)
    second = joined.patch_sample_index[a.n_vertices :]
    shift = ops[0].interpolation.shape[0]
    assert np.array_equal(
        second[:, :30], np.where(ops[1].patch_sample_index >= 0, ops[1].patch_sample_index + shift, -1)
    )
    assert np.all(second[:, 30:] == -1)


# ---------------------------------------------------------------------- files and cache
def test_save_load_round_trip(tmp_path):
    config = PatchConfig(r0=2.0, n_samples=800, inner_radius=0.3, precision="float32")
    op = build_patch_operator(bumpy_sphere(1), config)
    assert op.pairs.values.dtype == np.float64  # built without a cache: the fit's float64
    op.save(tmp_path / "op.zop")
    back = PatchOperator.load(tmp_path / "op.zop")
    # The file holds the sample geometry in float32 (indices in their narrowest types); the matrix fitted
    # from it again is held in the config's precision and equals the float64 one within float32 rounding.
    assert back.pairs.values.dtype == np.float32 and back.pairs.columns.dtype == np.uint16
    assert back.patch_samples.dtype == np.uint16 and back.patch_r.dtype == np.float32
    assert not back.patch_r.flags.writeable  # a view of the mapped file, not a copy
    assert np.array_equal(back.matrix.indices, op.matrix.indices)
    np.testing.assert_allclose(back.matrix.data, op.matrix.data, rtol=0, atol=1e-5 * np.abs(op.matrix.data).max())
    assert back.config == op.config and back.lam == pytest.approx(op.lam, rel=1e-6)
    assert np.array_equal(back.patch_sample_index, op.patch_sample_index)
    np.testing.assert_allclose(back.frames, op.frames, atol=1e-7)  # float32 in the file
    np.testing.assert_allclose(back.patch_radius, op.patch_radius, atol=1e-7)  # float32 in the file
    assert np.allclose(back.patch_basis, op.patch_basis, atol=1e-5)
    assert op.patch_radius[op.patch_sample_index >= 0].min() >= 0.3 / 2.0  # inner radius applied
    assert PatchConfig.from_dict(op.config.to_dict()) == op.config


@pytest.mark.parametrize("precision, tolerance", [("float32", 1e-6), ("float16", 1e-3), ("bfloat16", 8e-3)])
def test_stored_precisions_against_the_float32_csr_operator_of_format_4(tmp_path, precision, tolerance):
    # Format 4 stored the float32 CSR matrix and multiplied by it with torch; the compact operator read back
    # gives the same layer inputs within 1e-6 of their largest in float32 (asked: 1e-5), and a half
    # precision within its rounding (float16 about 2e-4, bfloat16 about 2e-3 measured).
    surface = bumpy_sphere(2)
    config = PatchConfig(r0=2.0, n_samples=2000, inner_radius=0.5, subtract_center=True, precision=precision)
    reference = build_patch_operator(surface, config).matrix.astype(np.float32)
    old = torch.sparse_csr_tensor(
        torch.from_numpy(reference.indptr.astype(np.int64)),
        torch.from_numpy(reference.indices.astype(np.int64)),
        torch.from_numpy(reference.data),
        size=reference.shape,
    )
    cached = build_patch_operator(surface, config, cache_dir=tmp_path)
    assert cached.pairs.precision == precision
    x = torch.randn(surface.n_vertices, 16, requires_grad=True)
    g = torch.randn(surface.n_vertices, cached.k, 16)
    got = cached.apply(x)
    (grad,) = torch.autograd.grad(got, x, g)
    expected = (old @ x.detach()).reshape(got.shape)
    expected_grad = old.t() @ g.reshape(-1, 16)
    assert (got.detach() - expected).abs().max() <= tolerance * expected.abs().max()
    assert (grad - expected_grad).abs().max() <= tolerance * expected_grad.abs().max()


def test_cache_hit_and_bad_files_are_rebuilt(tmp_path):
    surface = bumpy_sphere(1)
    config = PatchConfig(r0=2.0, n_samples=800)
    op = build_patch_operator(surface, config, cache_dir=tmp_path)
    path = tmp_path / f"{cache_key(surface, config)}.zop"
    assert path.exists() and op.matrix.dtype == np.float32  # returned as the file holds it
    again = build_patch_operator(surface, config, cache_dir=tmp_path)
    assert (again.matrix != op.matrix).nnz == 0

    good = path.read_bytes()
    other = build_patch_operator(surface, PatchConfig(r0=1.5, n_samples=800))
    damaged = bytearray(good)
    damaged[len(good) // 2] ^= 0xFF
    bad_files = {
        "corrupt": bytes(damaged),
        "truncated": good[: len(good) // 3],
        "stale key": other.to_bytes(key="0" * 64),
        "garbage": b"not an operator file",
        "empty": b"",
    }
    reasons = {"corrupt": "checksum mismatch", "truncated": "truncated", "stale key": "does not match"}
    for label, data in bad_files.items():
        path.write_bytes(data)
        with pytest.warns(CacheWarning, match=f"{path.name}.*{reasons.get(label, '')}"):
            rebuilt = build_patch_operator(surface, config, cache_dir=tmp_path)
        assert (rebuilt.matrix != op.matrix).nnz == 0, label
        assert path.read_bytes() != data  # the bad file was replaced by a good one


def test_version_mismatch_rejected(tmp_path, monkeypatch):
    import zernet.operators.cache as cache

    op = build_patch_operator(bumpy_sphere(1), PatchConfig(r0=2.0, n_samples=500))
    data = op.to_bytes(key="k")
    monkeypatch.setattr(cache, "FORMAT_VERSION", cache.FORMAT_VERSION + 1)
    with pytest.raises(ValueError, match="format version"):
        PatchOperator.from_bytes(data, key="k", name="somefile.npz")


def test_config_validation():
    with pytest.raises(ValueError):
        PatchConfig(r0=0.0)
    with pytest.raises(ValueError):
        PatchConfig(r0=1.0, backend="magic")
    with pytest.raises(ValueError):
        PatchConfig(r0=1.0, ridge=0.0)
    with pytest.raises(ValueError, match="precision"):
        PatchConfig(r0=1.0, precision="float64")  # the fit's own precision is not a storage option
    assert PatchConfig(r0=1.0).k == num_bases(5) == 21


def test_the_checksum_is_verified_once_per_file_version(tmp_path, monkeypatch):
    import hashlib

    import zernet.operators.cache as cache

    op = build_patch_operator(bumpy_sphere(1), PatchConfig(r0=2.0, n_samples=500)).as_cached()
    path, data = tmp_path / "op.zop", op.to_bytes(key="k")
    path.write_bytes(data)  # written by another process
    reference = op.matrix  # (numba loads its compiled kernels with sha256 too: before counting)
    hashed, sha256 = [], hashlib.sha256
    monkeypatch.setattr(cache.hashlib, "sha256", lambda data=b"": hashed.append(len(data)) or sha256(data))
    for _ in range(3):
        assert (PatchOperator.load(path, key="k").matrix != reference).nnz == 0
    assert len(hashed) == 1  # a streamed data set rereads its files every epoch
    path.write_bytes(data)
    os.utime(path, ns=(path.stat().st_atime_ns, path.stat().st_mtime_ns + 10**9))  # a rewritten file
    PatchOperator.load(path, key="k")
    assert len(hashed) == 2
    written = op.save(tmp_path / "mine.zop", key="k")  # written by this process: hashed as it was written
    assert len(hashed) == 3
    PatchOperator.load(written, key="k")
    assert len(hashed) == 3


@pytest.mark.parametrize("which", [0, 1])
def test_an_operator_file_of_an_older_format_is_named_and_rebuilt(tmp_path, which):
    from zernet.operators.cache import legacy_cache_paths

    surface, config = bumpy_sphere(1), PatchConfig(r0=2.0, n_samples=500)
    legacy = legacy_cache_paths(tmp_path, surface, config, "front")[which]  # format 4 (.zop), format 3 (.npz)
    legacy.write_bytes(b"an operator of an older format")
    with pytest.warns(CacheWarning, match=f"{legacy.name} is a patch operator cached in an older format"):
        op = build_patch_operator(surface, config, cache_dir=tmp_path)
    assert op.cache_file.suffix == ".zop" and op.cache_file.exists() and op.cache_file != legacy


# ---------------------------------------------------------------------- products
def test_reordered_rows_are_the_gathered_matrix():
    from zernet.operators.sparse import reorder_basis_rows

    op = build_patch_operator(bumpy_sphere(1), PatchConfig(r0=2.0, n_samples=600, n_max=3))
    order = np.random.default_rng(3).permutation(op.k)
    rows = (np.arange(op.n_vertices)[:, None] * op.k + order[None, :]).ravel()
    expected = op.matrix[rows].tocsr()
    reordered = reorder_basis_rows(op.matrix, op.k, order)
    assert (reordered != expected).nnz == 0 and np.array_equal(reordered.indptr, expected.indptr)


def test_a_loaded_operator_applies_and_backpropagates_from_its_pairs(tmp_path, monkeypatch):
    from zernet.operators.pairs import VertexPairs

    config = PatchConfig(r0=2.0, n_samples=600, n_max=3, precision="float32")
    op = build_patch_operator(bumpy_sphere(1), config, cache_dir=tmp_path)
    loaded = PatchOperator.load(op.cache_file)
    matrix = loaded.matrix.astype(np.float64)

    def must_not_run(*args, **kwargs):
        raise AssertionError("a product expanded the pairs into a matrix")

    monkeypatch.setattr(VertexPairs, "to_csr", must_not_run)
    order = tuple(np.random.default_rng(4).permutation(loaded.k).tolist())
    x = torch.randn(loaded.n_vertices, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(
        lambda v: loaded.apply(v, basis_order=order), (x,), eps=1e-6, atol=1e-8, fast_mode=True
    )
    g = torch.randn(loaded.n_vertices, loaded.k, 3, dtype=torch.float64)
    (grad,) = torch.autograd.grad(loaded.apply(x, basis_order=order), x, g)
    inverse = np.argsort(order)
    expected = matrix.T @ g[:, inverse].reshape(-1, 3).numpy()
    np.testing.assert_allclose(grad.numpy(), expected, rtol=1e-12, atol=1e-12)
    x32 = x.detach().float().requires_grad_()
    (grad32,) = torch.autograd.grad(loaded.apply(x32, basis_order=order), x32, g.float())
    np.testing.assert_allclose(grad32.numpy(), expected, rtol=1e-4, atol=1e-5)


def test_the_expanded_matrices_of_other_devices_are_the_pairs_products():
    # Off the CPU the pairs are expanded into a CSR matrix and its transpose for each product; the expansion
    # is device-independent torch, checked here on the CPU against the pairs' own products.
    ops = [build_patch_operator(bumpy_sphere(1, seed), PatchConfig(r0=2.0, n_samples=600, n_max=3)) for seed in (0, 1)]
    batch = PatchOperator.concatenate(ops)
    order = tuple(np.random.default_rng(6).permutation(batch.k).tolist())
    matrix, transpose = batch._expanded(torch.float64, torch.device("cpu"), order, transpose=True)
    x = torch.randn(batch.n_vertices, 4, dtype=torch.float64)
    g = torch.randn(batch.n_vertices, batch.k, 4, dtype=torch.float64)
    torch.testing.assert_close((matrix @ x).reshape(g.shape), batch.apply(x, basis_order=order))
    x.requires_grad_(True)
    (grad,) = torch.autograd.grad(batch.apply(x, basis_order=order), x, g)
    torch.testing.assert_close(transpose @ g.reshape(-1, 4), grad)
