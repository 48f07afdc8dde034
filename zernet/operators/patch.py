"""The patch operator: one sparse linear map from per-vertex features to local Zernike coefficients.

For vertex ``p`` with patch samples ``j`` at geodesic polar coordinates ``(r_j / r0, θ_j)``, the Zernike
coefficients of a field ``f`` are the ridge least-squares fit (piston unpenalised) ``a_p = P_p f(samples)``
with ``P_p = (B_pᵀ B_p + λ W)⁻¹ B_pᵀ`` (``B_p``: n_p × k Zernike values; ``W`` and λ in
:mod:`zernet.operators.fit`). Samples carry vertex features by barycentric interpolation, so the whole
map is ``A = blockrows_p(P_p · Interp[patch of p])``, an ``(N·k) × N`` CSR matrix built once per surface
and applied with a custom autograd function (:class:`SparseApply`) that keeps its transpose.

Patch selection (the sampling rule): by default (``patch_size=None``) a patch holds **every** sample
within ``r0`` (leaving out those with ``r < inner_radius``), so the samples cover the whole disk and the
fitted coefficients are the unit-disk Zernike coefficients (at 12,000 samples on area 15000 and r0 = 5.5
that is ~76 samples; the 50 nearest reach only ~0.8 r0). ``patch_size=n`` keeps the ``n`` nearest samples
(by geodesic radius) instead: ``patch_size=50`` is the paper's formulation.

The ridge does not bias a well-posed patch: the piston is not penalised (a constant field is fitted
exactly), the higher degrees are penalised more. Truncated patches (boundary vertices, vertices with
fewer than k samples) stay well-posed: the modes their samples cannot see shrink to 0 (the least-squares
counterpart of the paper's zero padding). A vertex with no sample within ``r0`` gets all-zero rows.

Polar backend: ``backend=None`` (default) takes ``"front"`` (surface distances by front propagation). A
point cloud is first triangulated through its own points (:func:`zernet.geometry.cloud_mesh.mesh_from_cloud`:
same vertices, so the operator is still ``(N·k) × N`` over the points) and sampled like a mesh.

``subtract_center``: the fit is of ``f(sample) − f(p)``, i.e. ``A_p ← A_p − (P_p 1) e_pᵀ`` (still linear).

Precision: the fit is computed in float64. An operator kept in the cache holds float32 values (the
precision the layers compute in; the file format is :mod:`zernet.operators.cache`), and
:func:`build_patch_operator` with a ``cache_dir`` returns the operator as the file holds it, whether it was
built now or read back; without a cache the float64 matrix is kept.

Cache: :func:`build_patch_operator` with ``cache_dir`` keeps one file per (geometry, config); the key and
the checked file format are in :mod:`zernet.operators.cache`; the key holds the backend actually used and
its version, so an operator built by an older backend or fit is rebuilt, never reused. A loaded operator's
arrays are views of the memory-mapped file: holding it costs page cache, and preparing its matrices for a
step is a copy of the arrays the layers read (the matrix and its stored transpose), never a transpose.
"""

from __future__ import annotations

import dataclasses
import os
import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse
import torch

from zernet.geometry import BACKENDS, Surface, compute_polar, resolve_backend, sample_surface
from zernet.geometry.cloud_mesh import mesh_from_cloud
from zernet.zernike import num_bases, zernike_basis

from .cache import (
    FORMAT_VERSION,
    CacheWarning,
    cache_key,
    cache_path,
    legacy_cache_path,
    pack_arrays,
    read_arrays,
    sparse_from_arrays,
    sparse_to_arrays,
    unpack_arrays,
    write_arrays,
)
from .fit import carry_to_vertices, fit_groups, fit_patches, ridge_weights
from .sparse import (
    SparseApply,
    basis_orders_of_size,
    block_diagonal_csr,
    canonical_device,
    checked_basis_order,
    csr_copy_to,
    csr_nbytes,
    pinned_csr,
    reorder_basis_columns,
    reorder_basis_rows,
    to_torch_csr,
    transpose_csr,
)

__all__ = [
    "PatchConfig",
    "PatchOperator",
    "build_patch_operator",
    "select_patches",
    "fit_patches",
    "assemble_operator",
]


@dataclass(frozen=True)
class PatchConfig:
    """Everything that determines a patch operator besides the surface.

    Attributes:
        r0: patch radius (absolute units; 5.5 for bodies at area 15000).
        n_samples: number of area-uniform surface samples (on a point cloud: used by the front, which
            samples its triangulation; ignored by "fast" and "accurate", which use the points).
        patch_size: ``None`` (default): every sample within ``r0`` (the patch covers the disk, so the fit gives
            the unit-disk coefficients); ``n``: the ``n`` nearest samples only (``50``: the paper's setting).
        n_max: highest Zernike degree (k = (n_max + 1)(n_max + 2) / 2; 5 -> 21).
        inner_radius: samples closer than this (absolute units) are left out.
        subtract_center: fit ``f(sample) - f(p)`` instead of ``f(sample)``.
        ridge: regularisation relative to a full patch's typical eigenvalue, on every basis but the piston
            (:mod:`zernet.operators.fit`).
        backend: polar-coordinate backend: ``None`` (default: ``"front"``), ``"front"`` (surface distances by
            front propagation; a point cloud is triangulated through its points first), ``"fast"`` or
            ``"accurate"``.
        seed: seed of the surface sampling.
    """

    r0: float
    n_samples: int = 12000
    patch_size: int | None = None
    n_max: int = 5
    inner_radius: float = 0.0
    subtract_center: bool = False
    ridge: float = 1e-3
    backend: str | None = None
    seed: int = 0

    def __post_init__(self) -> None:
        if not self.r0 > 0:
            raise ValueError(f"PatchConfig.r0 must be positive, got {self.r0}")
        if self.n_samples < 1 or (self.patch_size is not None and self.patch_size < 1) or self.n_max < 0:
            raise ValueError(f"PatchConfig needs n_samples >= 1, patch_size >= 1, n_max >= 0: {self}")
        if not 0 <= self.inner_radius < self.r0:
            raise ValueError(f"PatchConfig.inner_radius must be in [0, r0), got {self.inner_radius}")
        if not self.ridge > 0:
            raise ValueError(
                f"PatchConfig.ridge must be positive (it keeps truncated patches well-posed), got {self.ridge}"
            )
        if self.backend is not None and self.backend not in BACKENDS:
            raise ValueError(f"PatchConfig.backend must be None (automatic) or one of {BACKENDS}, got {self.backend!r}")

    @property
    def k(self) -> int:
        """Number of Zernike coefficients per vertex."""
        return num_bases(self.n_max)

    def to_dict(self) -> dict:
        """Plain dict (JSON-serialisable) of all fields."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, values: dict) -> PatchConfig:
        """Inverse of :meth:`to_dict`."""
        return cls(**values)


class PatchOperator:
    """Sparse map from per-vertex features to per-vertex Zernike coefficients, plus its patch data.

    Attributes:
        n_vertices: N.
        k: Zernike coefficients per vertex.
        n_max: highest Zernike degree.
        config: the :class:`PatchConfig` it was built with.
        matrix: scipy CSR (N·k, N), sorted indices; row ``p·k + j`` gives coefficient j at vertex p. float64
            as built, float32 as cached (module docstring).
        transpose: scipy CSR (N, N·k), ``matrix.T`` with sorted indices, in the matrix's dtype: what the
            backward of :meth:`apply` multiplies by. Built on first use (or given, e.g. read from the
            cache file) and kept.
        frames: (N, 3, 3) rows (e1, e2, normal); θ is measured from e1 towards e2.
        patch_sample_index: (N, n) int64 sample ids per patch, nearest first, -1 where a patch is shorter.
        patch_radius: (N, n) float64 normalised radius r / r0 (0 where -1).
        patch_angle: (N, n) float64 θ (0 where -1).
        interpolation: scipy CSR (M, N) vertex field -> samples.
        lam: the absolute ridge λ used.
        ridge_weights: (k,) the diagonal of the ridge's ``W``: 0 for the piston, 1 otherwise (:mod:`zernet.operators.fit`).
        cache_file: the cache file :func:`build_patch_operator` read it from or wrote it to (``None``
            otherwise); files derived from the operator, like its directional transport angles
            (:func:`zernet.operators.directional.patch_transport`), are kept beside it.
    """

    def __init__(
        self,
        matrix: scipy.sparse.csr_matrix,
        frames: np.ndarray,
        patch_sample_index: np.ndarray,
        patch_radius: np.ndarray,
        patch_angle: np.ndarray,
        interpolation: scipy.sparse.csr_matrix,
        config: PatchConfig,
        lam: float = 0.0,
        transpose: scipy.sparse.csr_matrix | None = None,
    ) -> None:
        matrix = matrix.tocsr()
        if not matrix.has_sorted_indices:
            matrix = matrix.copy()
            matrix.sort_indices()
        self.matrix = matrix
        self._transpose = None if transpose is None else transpose.tocsr()
        self.frames = frames
        self.patch_sample_index = patch_sample_index
        self.patch_radius = patch_radius
        self.patch_angle = patch_angle
        self.interpolation = interpolation.tocsr()
        self.config = config
        self.lam = float(lam)
        self.n_vertices = int(frames.shape[0])
        self.n_max = config.n_max
        self.k = config.k
        self.ridge_weights = ridge_weights(config.n_max)
        if self.matrix.shape != (self.n_vertices * self.k, self.n_vertices):
            raise ValueError(
                f"operator matrix has shape {self.matrix.shape}, expected {(self.n_vertices * self.k, self.n_vertices)}"
            )
        if self._transpose is not None and (
            self._transpose.shape != self.matrix.shape[::-1] or self._transpose.nnz != self.matrix.nnz
        ):
            raise ValueError(
                f"transpose has shape {self._transpose.shape} and {self._transpose.nnz} entries, "
                f"expected {self.matrix.shape[::-1]} and {self.matrix.nnz}"
            )
        self._tensors: dict[tuple, tuple[torch.Tensor, torch.Tensor]] = {}  # (dtype, device, basis order)
        self._parts: list[PatchOperator] = []  # the surfaces of a batch (set by concatenate)
        self._basis: np.ndarray | None = None
        self.cache_file: Path | None = None

    # ------------------------------------------------------------------ data
    @property
    def patch_basis(self) -> np.ndarray:
        """(N, n, k) float64 Zernike values at the patch samples (0 where the index is -1); computed on
        first use from :attr:`patch_radius` and :attr:`patch_angle`."""
        if self._basis is None:
            basis = zernike_basis(self.patch_radius, self.patch_angle, self.n_max)
            basis[self.patch_sample_index < 0] = 0.0
            self._basis = basis
        return self._basis

    @property
    def transpose(self) -> scipy.sparse.csr_matrix:
        """``matrix.T`` as sorted CSR (see the class docstring), built once and kept."""
        if self._transpose is None:
            self._transpose = transpose_csr(self.matrix)  # (a batch's is joined from its surfaces')
        return self._transpose

    @property
    def nnz(self) -> int:
        """Non-zeros of the matrix."""
        return sum(part.nnz for part in self._parts) if self._parts else int(self.matrix.nnz)

    def __repr__(self) -> str:
        return f"PatchOperator(N={self.n_vertices}, k={self.k}, nnz={self.nnz}, r0={self.config.r0})"

    # ------------------------------------------------------------------ apply
    # Operators accept ``apply(x, basis_order=...)`` (see :meth:`apply`); layers that consume the coefficients
    # in another order (the harmonic contraction, grouped by frequency) ask for it instead of gathering.
    accepts_basis_order = True

    def _torch_matrices(
        self, dtype: torch.dtype, device: torch.device, basis_order: tuple | None = None, transpose: bool = True
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """CSR tensors of A and Aᵀ (rows of A in ``basis_order`` within each vertex, the columns of Aᵀ
        likewise) for this dtype and device, built on first use and kept. Aᵀ is the stored
        :attr:`transpose`, never re-sorted; below float64 the arrays are cast first (half the bytes to
        reorder and move). With ``transpose=False`` Aᵀ is not built (None unless built before): a forward
        pass without gradients never reads it, and building it costs as much as A."""
        device = canonical_device(device)
        key = (dtype, device, basis_order)
        held = self._tensors.get(key)
        if held is not None and (held[1] is not None or not transpose):
            return held
        if self._parts:  # a batch: its surfaces' own tensors, stacked
            built = [part._torch_matrices(dtype, device, basis_order, transpose) for part in self._parts]
            matrix = held[0] if held is not None else block_diagonal_csr([b[0] for b in built])
            self._tensors[key] = (matrix, block_diagonal_csr([b[1] for b in built]) if transpose else None)
            return self._tensors[key]
        matrix = held[0] if held is not None else to_torch_csr(self._host_csr(False, dtype, basis_order), dtype, device)
        self._tensors[key] = (
            matrix,
            to_torch_csr(self._host_csr(True, dtype, basis_order), dtype, device) if transpose else None,
        )
        return self._tensors[key]

    def _host_csr(self, transposed: bool, dtype: torch.dtype, basis_order: tuple | None) -> scipy.sparse.csr_matrix:
        """A or Aᵀ on the host, cast to float32 below float64 and in ``basis_order``."""
        matrix = self.transpose if transposed else self.matrix
        if dtype != torch.float64 and matrix.dtype == np.float64:
            matrix = matrix.astype(np.float32)
        if basis_order is not None:
            reorder = reorder_basis_columns if transposed else reorder_basis_rows
            matrix = reorder(matrix, self.k, basis_order)
        return matrix

    def apply(self, x: torch.Tensor, basis_order: tuple | None = None) -> torch.Tensor:
        """Zernike coefficients of the features' local patches.

        Args:
            x: (N,) or (N, *C) tensor; any floating dtype and device.
            basis_order: optional permutation of ``range(k)``: coefficient ``i`` of the output is basis
                ``basis_order[i]`` (the same as ``apply(x)[:, basis_order]``, without the gather; the
                reordered matrix is built once and kept).

        Returns:
            (N, k) or (N, k, *C), same dtype and device; differentiable in ``x``.
        """
        if x.shape[0] != self.n_vertices:
            raise ValueError(f"features have {x.shape[0]} rows but the operator has {self.n_vertices} vertices")
        trailing = x.shape[1:]
        flat = x.reshape(self.n_vertices, -1)
        needs_transpose = torch.is_grad_enabled() and flat.requires_grad  # only the backward reads Aᵀ
        order = checked_basis_order(basis_order, self.k)
        matrix, transpose = self._torch_matrices(x.dtype, x.device, order, needs_transpose)
        out = SparseApply.apply(flat.contiguous(), matrix, transpose)
        return out.reshape((self.n_vertices, self.k) + tuple(trailing))

    __call__ = apply

    def to(self, device, basis_orders: Sequence[tuple] = ()) -> PatchOperator:
        """Move the cached torch tensors to ``device`` (the next :meth:`apply` there needs no conversion).

        ``basis_orders``: the orders the model's layers will ask :meth:`apply` for
        (:meth:`zernet.nn.ZernikeConv.operator_basis_order`; orders of another ``k`` are skipped); their
        float32 tensors are built now, so a data pipeline pays for them on its read-ahead thread, not
        inside the forward pass. Without any, the natural order is built.

        Returns ``self``; the numpy/scipy data stay on the host. Tensors for other devices are dropped.
        """
        device = canonical_device(device)
        for part in self._parts:
            part.to(device, basis_orders)
        wanted = {(torch.float32, order) for order in basis_orders_of_size(basis_orders, self.k)}
        if self._tensors and all(have == device for _, have, _ in self._tensors):
            for dtype, order in wanted:  # already there (training calls this every step): add what is missing
                self._torch_matrices(dtype, device, order)
            return self
        kinds = {(dtype, order) for dtype, _, order in self._tensors} | wanted or {(torch.float32, None)}
        self._tensors = {}
        for dtype, order in kinds:
            self._torch_matrices(dtype, device, order)
        return self

    def copy_to(self, device, non_blocking: bool = False) -> PatchOperator:
        """A copy whose prepared tensors (:meth:`to`) are on ``device``, sharing the host arrays; this one
        keeps its own. With ``non_blocking`` and pinned tensors (:meth:`pin_memory`) the copies to a GPU run
        asynchronously (a host-resident record copied for one step, :mod:`zernet.training.residency`)."""
        device = canonical_device(device)
        copy = PatchOperator.__new__(PatchOperator)
        copy.__dict__.update(self.__dict__)
        copy._parts = [part.copy_to(device, non_blocking) for part in self._parts]
        copy._tensors = {
            (dtype, device, order): tuple(None if m is None else csr_copy_to(m, device, non_blocking) for m in matrices)
            for (dtype, _, order), matrices in self._tensors.items()
        }
        return copy

    def pin_memory(self) -> PatchOperator:
        """Put the prepared host tensors in page-locked memory (CUDA only); returns ``self``."""
        for part in self._parts:
            part.pin_memory()
        self._tensors = {
            key: tuple(pinned_csr(m) if m is not None and m.device.type == "cpu" else m for m in matrices)
            for key, matrices in self._tensors.items()
        }
        return self

    @property
    def prepared_nbytes(self) -> int:
        """Bytes of the prepared torch tensors (:meth:`to`) this operator holds."""
        own = sum(csr_nbytes(m) for matrices in self._tensors.values() for m in matrices if m is not None)
        return own if not self._parts else sum(part.prepared_nbytes for part in self._parts)

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_tensors"] = {}  # torch tensors are rebuilt on demand after unpickling
        state["_basis"] = None
        return state

    def __setstate__(self, state):
        state.setdefault("_parts", [])  # pickled by an older version
        self.__dict__.update(state)

    # ------------------------------------------------------------------ batching
    @staticmethod
    def concatenate(ops: list[PatchOperator]) -> PatchOperator:
        """Block-diagonal operator of several surfaces (vertices and samples stacked in order).

        All operators must have the same ``k``; the result carries the first operator's config. Its torch
        tensors stack the surfaces' own prepared tensors (:meth:`to`; no host work when they are already
        on the device), and its host arrays (``matrix``, the patch arrays padded to the longest patch with
        -1 / 0, ``interpolation``) are joined on first access only.
        """
        ops = [part for op in ops for part in (op._parts or [op])]
        if not ops:
            raise ValueError("concatenate needs at least one operator")
        if len({op.k for op in ops}) != 1:
            raise ValueError(f"cannot concatenate operators with different k: {[op.k for op in ops]}")
        batch = PatchOperator.__new__(PatchOperator)
        batch.__dict__.update(
            config=ops[0].config,
            lam=ops[0].lam,
            n_vertices=sum(op.n_vertices for op in ops),
            n_max=ops[0].n_max,
            k=ops[0].k,
            ridge_weights=ops[0].ridge_weights,
            _tensors={},
            _parts=ops,
            _basis=None,
            cache_file=None,
        )
        return batch

    #: Host arrays of a batch (:meth:`concatenate`), joined from its surfaces on first access.
    _JOINED = ("matrix", "_transpose", "frames", "patch_sample_index", "patch_radius", "patch_angle", "interpolation")

    def __getattr__(self, name):
        # Called only for attributes not set: the host arrays of a batch, joined once from its surfaces.
        parts = self.__dict__.get("_parts")
        if not parts or name not in PatchOperator._JOINED:
            raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")
        self.__dict__.update(_joined_arrays(parts))
        return self.__dict__[name]

    # ------------------------------------------------------------------ files
    def to_arrays(self) -> tuple[dict[str, np.ndarray], dict]:
        """Everything that defines the operator as ``(arrays, meta)``: named numpy arrays and JSON values
        (the cache file's content). The matrix and its transpose in the layout the layers read: float32
        values, int32 indices where they fit, sorted."""
        arrays = {
            "frames": self.frames,
            "patch_sample_index": self.patch_sample_index,
            "patch_radius": self.patch_radius,
            "patch_angle": self.patch_angle,
        }
        for name, matrix in (("matrix", self.matrix), ("transpose", self.transpose)):
            arrays.update(sparse_to_arrays(name, matrix.astype(np.float32)))
        arrays.update(sparse_to_arrays("interpolation", self.interpolation))
        return arrays, {"config": self.config.to_dict(), "lam": self.lam}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], meta: dict, name: str = "<arrays>") -> PatchOperator:
        """Inverse of :meth:`to_arrays` over the same arrays (no copy); ``ValueError`` naming ``name`` if they
        do not fit together."""
        try:
            return cls(
                matrix=sparse_from_arrays(arrays, "matrix", sorted_indices=True),
                transpose=sparse_from_arrays(arrays, "transpose", sorted_indices=True),
                frames=arrays["frames"],
                patch_sample_index=arrays["patch_sample_index"],
                patch_radius=arrays["patch_radius"],
                patch_angle=arrays["patch_angle"],
                interpolation=sparse_from_arrays(arrays, "interpolation"),
                config=PatchConfig.from_dict(dict(meta["config"])),
                lam=float(meta["lam"]),
            )
        except Exception as error:  # noqa: BLE001
            raise ValueError(f"{name}: inconsistent operator payload ({type(error).__name__}: {error})") from error

    def as_cached(self) -> PatchOperator:
        """The operator as its cache file holds it (float32 matrix and transpose), without writing one."""
        arrays, meta = self.to_arrays()
        return PatchOperator.from_arrays(arrays, meta)

    def to_bytes(self, key: str = "") -> bytes:
        """The bytes of its cache file (:func:`zernet.operators.cache.pack_arrays`)."""
        arrays, meta = self.to_arrays()
        return bytes(pack_arrays(arrays, key, meta))

    @classmethod
    def from_bytes(cls, data: bytes, key: str | None = None, name: str = "<bytes>") -> PatchOperator:
        """Inverse of :meth:`to_bytes`; raises ``ValueError`` (naming ``name``) on any inconsistency."""
        return cls.from_arrays(*unpack_arrays(data, key=key, name=name), name=name)

    def save(self, path: str | os.PathLike, key: str = "") -> Path:
        """Write its cache file atomically to ``path`` (:func:`zernet.operators.cache.write_arrays`)."""
        arrays, meta = self.to_arrays()
        return write_arrays(path, arrays, key, meta)

    @classmethod
    def load(cls, path: str | os.PathLike, key: str | None = None) -> PatchOperator:
        """Map a file written by :meth:`save`; ``ValueError`` naming the file if it cannot be trusted."""
        return cls.from_arrays(*read_arrays(path, key=key), name=str(path))


def _joined_arrays(ops: list[PatchOperator]) -> dict:
    """The host arrays of the block-diagonal operator of ``ops`` (see :meth:`PatchOperator.concatenate`)."""
    width = max(op.patch_sample_index.shape[1] for op in ops)
    sample_offset = np.cumsum([0] + [op.interpolation.shape[0] for op in ops])[:-1]

    def pad(array, fill):
        out = np.full((array.shape[0], width), fill, dtype=array.dtype)
        out[:, : array.shape[1]] = array
        return out

    index = np.concatenate(
        [
            pad(np.where(op.patch_sample_index >= 0, op.patch_sample_index + off, -1), -1)
            for op, off in zip(ops, sample_offset)
        ]
    )
    matrix = scipy.sparse.block_diag([op.matrix for op in ops], format="csr")
    matrix.has_sorted_indices = True  # blocks of sorted rows, column offsets increasing
    return {
        "matrix": matrix,
        "_transpose": scipy.sparse.block_diag([op.transpose for op in ops], format="csr"),
        "frames": np.concatenate([op.frames for op in ops]),
        "patch_sample_index": index,
        "patch_radius": np.concatenate([pad(op.patch_radius, 0.0) for op in ops]),
        "patch_angle": np.concatenate([pad(op.patch_angle, 0.0) for op in ops]),
        "interpolation": scipy.sparse.block_diag([op.interpolation for op in ops], format="csr"),
    }


# ====================================================================== building
def build_patch_operator(
    surface: Surface,
    config: PatchConfig,
    cache_dir: str | os.PathLike | None = None,
    progress: bool = False,
    n_jobs: int | None = None,
) -> PatchOperator:
    """Build (or load from the cache) the patch operator of a surface.

    Args:
        surface: mesh or point cloud.
        config: :class:`PatchConfig`.
        cache_dir: folder of cached operators (``<key>.zop``); ``None`` disables caching.
        progress: print the stage timings.
        n_jobs: worker processes of the accurate backend (``None``: all cores).

    Returns:
        :class:`PatchOperator`: with a ``cache_dir``, as its file holds it (float32; module docstring).
    """
    backend = resolve_backend(surface, config.backend)
    if backend == "front":
        surface = mesh_from_cloud(surface)  # a mesh is returned unchanged
    key = cache_key(surface, config, backend)
    path = None
    if cache_dir is not None:
        path = cache_path(cache_dir, key)
        if path.exists():
            try:
                operator = PatchOperator.load(path, key=key)
                operator.cache_file = path
                return operator
            except (ValueError, OSError) as error:
                warnings.warn(f"rebuilding cached patch operator {path}: {error}", CacheWarning, stacklevel=2)
        legacy = legacy_cache_path(cache_dir, surface, config, backend)
        if legacy.exists():
            warnings.warn(
                f"{legacy} is a patch operator cached in an older format; rebuilding it in format "
                f"{FORMAT_VERSION} as {path.name} (the old file is no longer read and can be deleted)",
                CacheWarning,
                stacklevel=2,
            )
    start = time.perf_counter()
    samples = sample_surface(surface, config.n_samples, seed=config.seed)
    polar = compute_polar(surface, samples, config.r0, backend=backend, n_jobs=n_jobs)
    if progress:
        print(f"{surface.name}: polar coordinates ({backend}) {polar.seconds:.2f} s, {polar.n_pairs} pairs")
    operator = assemble_operator(
        polar.center, polar.sample, polar.radius, polar.angle, polar.frames, samples.interpolation, config
    )
    if progress:
        print(f"{surface.name}: operator {operator} in {time.perf_counter() - start:.2f} s")
    if path is not None:
        operator.save(path, key=key)
        operator = operator.as_cached()
        operator.cache_file = path
    return operator


def select_patches(center, sample, radius, angle, n_vertices: int, config: PatchConfig):
    """The samples of each patch: all with ``inner_radius <= r <= r0``, or the ``patch_size`` nearest of them.

    Args:
        center, sample, radius, angle: (P,) pairs sorted by (center, radius), as in ``PolarCoordinates``.

    Returns:
        ``(index, r, theta)``, each (N, n): sample ids (-1 for padding), normalised radii r / r0 and angles
        (0 for padding), nearest first. ``n`` is the longest patch.
    """
    keep = (radius >= config.inner_radius) & (radius <= config.r0)
    center, sample, radius, angle = center[keep], sample[keep], radius[keep], angle[keep]
    start = np.searchsorted(center, np.arange(n_vertices))
    rank = np.arange(len(center)) - start[center]
    keep = rank < (config.patch_size if config.patch_size is not None else len(rank) + 1)
    center, sample, radius, angle, rank = center[keep], sample[keep], radius[keep], angle[keep], rank[keep]
    width = int(rank.max()) + 1 if len(rank) else 1
    index = np.full((n_vertices, width), -1, dtype=np.int64)
    r = np.zeros((n_vertices, width))
    theta = np.zeros((n_vertices, width))
    index[center, rank] = sample
    r[center, rank] = radius / config.r0
    theta[center, rank] = angle
    return index, r, theta


def assemble_operator(center, sample, radius, angle, frames, interpolation, config: PatchConfig) -> PatchOperator:
    """Patch selection, fit and the sparse operator ``A = blockrows(P_p · Interp[patch p])``.

    Args:
        center, sample, radius, angle: (P,) polar pairs sorted by (center, radius).
        frames: (N, 3, 3).
        interpolation: (M, N) CSR.
        config: :class:`PatchConfig`.

    Returns:
        :class:`PatchOperator`.
    """
    index, r, theta = select_patches(center, sample, radius, angle, frames.shape[0], config)
    counts = (index >= 0).sum(axis=1)
    groups, lam = fit_groups(r, theta, counts, config.n_max, config.ridge)
    matrix = carry_to_vertices(groups, index, interpolation, config.k, config.subtract_center)
    matrix.eliminate_zeros()
    return PatchOperator(
        matrix=matrix,
        frames=frames,
        patch_sample_index=index,
        patch_radius=r,
        patch_angle=theta,
        interpolation=interpolation,
        config=config,
        lam=lam,
    )
