"""The patch operator: one sparse linear map from per-vertex features to local Zernike coefficients.

For vertex ``p`` with patch samples ``j`` at geodesic polar coordinates ``(r_j / r0, θ_j)``, the Zernike
coefficients of a field ``f`` are the ridge least-squares fit (piston unpenalised) ``a_p = P_p f(samples)``
with ``P_p = (B_pᵀ B_p + λ W)⁻¹ B_pᵀ`` (``B_p``: n_p × k Zernike values; ``W`` and λ in
:mod:`zernet.operators.fit`). Samples carry vertex features by barycentric interpolation, so the whole
map is ``A = blockrows_p(P_p · Interp[patch of p])``, an ``(N·k) × N`` CSR matrix built once per surface
and applied with a custom autograd function (:class:`~zernet.operators.pairs.PairApply`) on the CPU.

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

Storage: the matrix is kept as vertex pairs ``(p, q)`` with the ``k`` values of each
(:mod:`zernet.operators.pairs`): a vertex's ``k`` rows read the same vertices, so this is the matrix
without its repeated indices, and the products read it directly (no stored transpose).

Precision: the fit is computed in float64. An operator kept in the cache holds its values in
``PatchConfig.precision`` (float16 by default; the file format is :mod:`zernet.operators.cache`), and
:func:`build_patch_operator` with a ``cache_dir`` returns the operator as the file holds it, whether it was
built now or read back; without a cache the float64 values are kept. The layers compute in float32 (or
float64) whatever the stored precision.

Cache: :func:`build_patch_operator` with ``cache_dir`` keeps one file per (geometry, config); the key and
the checked file format are in :mod:`zernet.operators.cache`; the key holds the backend actually used and
its version, so an operator built by an older backend or fit is rebuilt, never reused. The file holds the
patches' sample geometry, not the matrix (5 MB for a 6,890-vertex body with the FAUST settings, against
19 MB of float16 pairs): reading it fits the patches again (about 0.4 s there at two threads); on the CPU
the forward and the backward read those pairs as they are, so nothing else is built for a step.
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
    legacy_cache_paths,
    pack_arrays,
    read_arrays,
    sparse_from_arrays,
    sparse_to_arrays,
    unpack_arrays,
    write_arrays,
)
from .fit import carry_to_vertices, fit_groups, fit_patches, ridge_weights
from .pairs import PRECISIONS, PairApply, VertexPairs, expanded_csr, narrow_index_dtype, narrow_indptr
from .sparse import SparseApply, basis_orders_of_size, block_diagonal_csr, canonical_device, checked_basis_order

#: The precisions a cached operator's values can be stored in (``PatchConfig.precision``).
STORED_PRECISIONS = tuple(p for p in PRECISIONS if p != "float64")

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
        precision: how the operator cache stores the matrix's values: ``"float16"`` (default: half the
            bytes of float32; layer outputs within about 2e-4 of the float32 operator's, relative to their
            largest), ``"float32"`` or ``"bfloat16"`` (about 2e-3). The fit is float64 whatever it is.
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
    precision: str = "float16"

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
        if self.precision not in STORED_PRECISIONS:
            raise ValueError(f"PatchConfig.precision must be one of {STORED_PRECISIONS}, got {self.precision!r}")
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
        pairs: the matrix ``A`` ``(N·k, N)`` as vertex pairs with ``k`` values each
            (:class:`~zernet.operators.pairs.VertexPairs`): float64 as built, ``config.precision`` as cached
            (module docstring). Row ``p·k + j`` of ``A`` gives coefficient j at vertex p.
        frames: (N, 3, 3) rows (e1, e2, normal); θ is measured from e1 towards e2.
        interpolation: scipy CSR (M, N) vertex field -> samples.
        lam: the absolute ridge λ used.
        ridge_weights: (k,) the diagonal of the ridge's ``W``: 0 for the piston, 1 otherwise (:mod:`zernet.operators.fit`).
        cache_file: the cache file :func:`build_patch_operator` read it from or wrote it to (``None``
            otherwise); files derived from the operator, like its directional transport angles
            (:func:`zernet.operators.directional.patch_transport`), are kept beside it.

    The patch samples (:attr:`patch_sample_index`, :attr:`patch_radius`, :attr:`patch_angle`) are kept as
    one flat list per patch (``patch_indptr``, ``patch_samples``, ``patch_r``, ``patch_theta``: nearest
    first) and padded into ``(N, n)`` arrays when asked for.
    """

    def __init__(
        self,
        pairs: VertexPairs,
        frames: np.ndarray,
        patch_sample_index: np.ndarray,
        patch_radius: np.ndarray,
        patch_angle: np.ndarray,
        interpolation: scipy.sparse.csr_matrix,
        config: PatchConfig,
        lam: float = 0.0,
    ) -> None:
        valid = patch_sample_index >= 0
        counts = valid.sum(axis=1)
        if np.any(valid[:, 1:] & ~valid[:, :-1]):
            raise ValueError("patch_sample_index must hold each patch's samples first, then -1")
        patch_indptr = np.zeros(len(counts) + 1, dtype=np.int64)
        np.cumsum(counts, out=patch_indptr[1:])
        n_samples = interpolation.shape[0]
        self._init(
            pairs,
            frames,
            (
                narrow_indptr(patch_indptr),
                patch_sample_index[valid].astype(narrow_index_dtype(max(n_samples - 1, 0))),
                patch_radius[valid],
                patch_angle[valid],
            ),
            interpolation,
            config,
            lam,
        )

    def _init(self, pairs, frames, patches, interpolation, config, lam) -> None:
        """Set every attribute from the compact patch lists ``(indptr, samples, r, theta)``."""
        self.pairs = pairs
        self.frames = frames
        self.patch_indptr, self.patch_samples, self.patch_r, self.patch_theta = patches
        self.interpolation = interpolation.tocsr()
        self.config = config
        self.lam = float(lam)
        self.n_vertices = int(frames.shape[0])
        self.n_max = config.n_max
        self.k = config.k
        self.ridge_weights = ridge_weights(config.n_max)
        if (pairs.n_vertices, pairs.k) != (self.n_vertices, self.k):
            raise ValueError(
                f"operator pairs are for {pairs.n_vertices} vertices and k = {pairs.k}, expected "
                f"{self.n_vertices} and {self.k}"
            )
        if self.patch_indptr.shape[0] != self.n_vertices + 1 or self.patch_indptr[-1] != len(self.patch_samples):
            raise ValueError("the patch lists do not fit the vertices")
        self._devices: dict[torch.device, dict[str, torch.Tensor]] = {}  # the pairs as tensors, off the CPU
        self._parts: list[PatchOperator] = []  # the surfaces of a batch (set by concatenate)
        self._basis: np.ndarray | None = None
        self._padded: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self.cache_file: Path | None = None

    # ------------------------------------------------------------------ data
    def _padded_patches(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(index, r, theta)`` (N, n) padded with -1 / 0, built on first use and kept."""
        if self._padded is None:
            if self._parts:
                self._padded = _joined_patches(self._parts)
            else:
                self._padded = padded_patches(
                    self.patch_indptr, self.patch_samples, self.patch_r, self.patch_theta, self.n_vertices
                )
        return self._padded

    @property
    def patch_sample_index(self) -> np.ndarray:
        """(N, n) int64 sample ids per patch, nearest first, -1 where a patch is shorter."""
        return self._padded_patches()[0]

    @property
    def patch_radius(self) -> np.ndarray:
        """(N, n) float64 normalised radius r / r0 (0 where the index is -1)."""
        return self._padded_patches()[1]

    @property
    def patch_angle(self) -> np.ndarray:
        """(N, n) float64 θ (0 where the index is -1)."""
        return self._padded_patches()[2]

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
    def matrix(self) -> scipy.sparse.csr_matrix:
        """``A`` as a scipy CSR matrix ``(N·k, N)`` with sorted indices (float32 for a stored half
        precision), built from the pairs on every access: hold it if you read it more than once."""
        if self._parts:
            matrix = scipy.sparse.block_diag([part.matrix for part in self._parts], format="csr")
            matrix.has_sorted_indices = True  # blocks of sorted rows, column offsets increasing
            return matrix
        return self.pairs.to_csr()

    @property
    def nnz(self) -> int:
        """Stored entries of the matrix: ``k`` per vertex pair."""
        return sum(part.nnz for part in self._parts) if self._parts else self.pairs.n_pairs * self.k

    def __repr__(self) -> str:
        return f"PatchOperator(N={self.n_vertices}, k={self.k}, nnz={self.nnz}, r0={self.config.r0})"

    # ------------------------------------------------------------------ apply
    # Operators accept ``apply(x, basis_order=...)`` (see :meth:`apply`); layers that consume the coefficients
    # in another order (the harmonic contraction, grouped by frequency) ask for it instead of gathering.
    accepts_basis_order = True

    def _surfaces(self) -> list[PatchOperator]:
        return self._parts or [self]

    def apply(self, x: torch.Tensor, basis_order: tuple | None = None) -> torch.Tensor:
        """Zernike coefficients of the features' local patches.

        Args:
            x: (N,) or (N, *C) tensor; any floating dtype and device.
            basis_order: optional permutation of ``range(k)``: coefficient ``i`` of the output is basis
                ``basis_order[i]`` (the same as ``apply(x)[:, basis_order]``, without the gather).

        Returns:
            (N, k) or (N, k, *C), same dtype and device; differentiable in ``x``. On the CPU the product
            reads the pairs (:class:`~zernet.operators.pairs.PairApply`, float32 or float64 as ``x``); on
            another device it expands them there (:func:`~zernet.operators.pairs.expanded_csr`).
        """
        if x.shape[0] != self.n_vertices:
            raise ValueError(f"features have {x.shape[0]} rows but the operator has {self.n_vertices} vertices")
        trailing = x.shape[1:]
        flat = x.reshape(self.n_vertices, -1)
        order = checked_basis_order(basis_order, self.k)
        order = tuple(range(self.k)) if order is None else order
        if x.device.type == "cpu":
            compute = x.dtype if x.dtype in (torch.float32, torch.float64) else torch.float32
            parts = [part.pairs for part in self._surfaces()]
            out = PairApply.apply(flat.to(compute).contiguous(), parts, np.asarray(order, dtype=np.int64)).to(x.dtype)
        else:
            needs_transpose = torch.is_grad_enabled() and flat.requires_grad  # only the backward reads Aᵀ
            matrix, transpose = self._expanded(x.dtype, x.device, order, needs_transpose)
            out = SparseApply.apply(flat.contiguous(), matrix, transpose)
        return out.reshape((self.n_vertices, self.k) + tuple(trailing))

    __call__ = apply

    def _expanded(self, dtype, device, order: tuple, transpose: bool):
        """``(A, Aᵀ)`` as torch CSR on ``device`` (Aᵀ ``None`` unless ``transpose``), from the pairs held
        there (:meth:`to`), for this product only."""
        device = canonical_device(device)
        built = []
        for part in self._surfaces():
            tensors = part._devices.get(device)
            if tensors is None:
                tensors = part._devices[device] = {n: t.to(device) for n, t in part.pairs.torch_arrays().items()}
            built.append(expanded_csr(tensors, self.k, part.n_vertices, dtype, order, transpose))
        matrix = block_diagonal_csr([b[0] for b in built])
        return matrix, (block_diagonal_csr([b[1] for b in built]) if transpose else None)

    def to(self, device, basis_orders: Sequence[tuple] = ()) -> PatchOperator:
        """Prepare the operator for products on ``device``: on the CPU nothing (the products read the pairs
        where they are); elsewhere the pairs as tensors on that device (those of other devices are dropped).

        ``basis_orders`` (the orders the model's layers will ask :meth:`apply` for) cost nothing to prepare:
        a basis order is read from the pairs' values as they are; it is accepted like other operators'.
        Returns ``self``."""
        device = canonical_device(device)
        basis_orders_of_size(basis_orders, self.k)  # checked: an order that is no permutation is an error
        for part in self._parts:
            part.to(device, basis_orders)
        if self._parts:
            return self
        self._devices = {d: t for d, t in self._devices.items() if d == device or d.type == "cpu"}
        if device.type != "cpu" and device not in self._devices:
            self._devices[device] = {name: t.to(device) for name, t in self.pairs.torch_arrays().items()}
        return self

    def copy_to(self, device, non_blocking: bool = False) -> PatchOperator:
        """A copy whose pairs are held on ``device``, sharing the host arrays; this one keeps its own. With
        ``non_blocking`` and pinned tensors (:meth:`pin_memory`) the copies to a GPU run asynchronously (a
        host-resident record copied for one step, :mod:`zernet.training.residency`)."""
        device = canonical_device(device)
        copy = PatchOperator.__new__(PatchOperator)
        copy.__dict__.update(self.__dict__)
        copy._parts = [part.copy_to(device, non_blocking) for part in self._parts]
        if not self._parts and device.type != "cpu":  # on the CPU the products read the shared pairs
            source = self._devices.get(torch.device("cpu")) or self.pairs.torch_arrays()
            copy._devices = {device: {n: t.to(device, non_blocking=non_blocking) for n, t in source.items()}}
        return copy

    def pin_memory(self) -> PatchOperator:
        """Hold the pairs as page-locked host tensors (CUDA only: the copies of :meth:`copy_to` then run
        asynchronously); returns ``self``."""
        for part in self._parts:
            part.pin_memory()
        if not self._parts:
            self._devices[torch.device("cpu")] = {n: t.pin_memory() for n, t in self.pairs.torch_arrays().items()}
        return self

    @property
    def prepared_nbytes(self) -> int:
        """Bytes this operator holds for products: its pairs and their copies as tensors (:meth:`to`, :meth:`pin_memory`)."""
        if self._parts:
            return sum(part.prepared_nbytes for part in self._parts)
        return self.pairs.nbytes + sum(VertexPairs.torch_nbytes(t) for t in self._devices.values())

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_devices"] = {}  # tensors are rebuilt on demand after unpickling
        state["_basis"] = None
        state["_padded"] = None
        return state

    # ------------------------------------------------------------------ batching
    @staticmethod
    def concatenate(ops: list[PatchOperator]) -> PatchOperator:
        """Block-diagonal operator of several surfaces (vertices and samples stacked in order).

        All operators must have the same ``k``; the result carries the first operator's config. Its products
        read the surfaces' own pairs (no copy), and its host arrays (``frames``, ``interpolation``, the patch
        arrays padded to the longest patch with -1 / 0) are joined on first access only.
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
            _devices={},
            _parts=ops,
            _basis=None,
            _padded=None,
            cache_file=None,
        )
        return batch

    #: Host arrays of a batch (:meth:`concatenate`), joined from its surfaces on first access.
    _JOINED = ("frames", "interpolation")

    def __getattr__(self, name):
        # Called only for attributes not set: the host arrays of a batch, joined once from its surfaces.
        parts = self.__dict__.get("_parts")
        if not parts or name not in PatchOperator._JOINED:
            raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")
        self.__dict__.update(
            frames=np.concatenate([op.frames for op in parts]),
            interpolation=scipy.sparse.block_diag([op.interpolation for op in parts], format="csr"),
        )
        return self.__dict__[name]

    # ------------------------------------------------------------------ files
    def to_arrays(self) -> tuple[dict[str, np.ndarray], dict]:
        """Everything that defines the operator as ``(arrays, meta)``: named numpy arrays and JSON values
        (the cache file's content). Not the matrix: its patches' sample geometry (the flat patch lists with
        radii and angles in float32), the interpolation (float32) and the frames (float32), from which
        :meth:`from_arrays` fits the matrix again; indices in their narrowest types."""
        interpolation = self.interpolation.astype(np.float32)
        arrays = {
            "frames": np.asarray(self.frames, dtype=np.float32),
            "patch_indptr": self.patch_indptr,
            "patch_samples": self.patch_samples,
            "patch_r": np.asarray(self.patch_r, dtype=np.float32),
            "patch_theta": np.asarray(self.patch_theta, dtype=np.float32),
        }
        arrays.update(sparse_to_arrays("interpolation", interpolation))
        return arrays, {"config": self.config.to_dict(), "lam": self.lam, "precision": self.config.precision}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], meta: dict, name: str = "<arrays>") -> PatchOperator:
        """Inverse of :meth:`to_arrays` over the same arrays (no copy of them): the patches are fitted again
        and carried to the vertices (:func:`fit_pairs`, about half a second for a 6,890-vertex body on two
        threads), the pairs kept in ``meta["precision"]``; ``ValueError`` naming ``name`` if the arrays do not
        fit together."""
        try:
            config = PatchConfig.from_dict(dict(meta["config"]))
            frames = arrays["frames"]
            patches = (arrays["patch_indptr"], arrays["patch_samples"], arrays["patch_r"], arrays["patch_theta"])
            interpolation = sparse_from_arrays(arrays, "interpolation")
            if patches[0].shape != (frames.shape[0] + 1,) or int(patches[0][-1]) != len(patches[1]):
                raise ValueError("the patch lists do not fit the vertices")
            pairs, lam = fit_pairs(*padded_patches(*patches, frames.shape[0]), interpolation, config)
            operator = cls.__new__(cls)
            operator._init(pairs.with_precision(meta["precision"]), frames, patches, interpolation, config, lam)
            return operator
        except Exception as error:  # noqa: BLE001
            raise ValueError(f"{name}: inconsistent operator payload ({type(error).__name__}: {error})") from error

    def as_cached(self) -> PatchOperator:
        """The operator as its cache file holds it (values in ``config.precision``), without writing one."""
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


def _joined_patches(ops: list[PatchOperator]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The padded patch arrays of the block-diagonal operator of ``ops`` (:meth:`PatchOperator.concatenate`)."""
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
    radius = np.concatenate([pad(op.patch_radius, 0.0) for op in ops])
    return index, radius, np.concatenate([pad(op.patch_angle, 0.0) for op in ops])


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
        for legacy in legacy_cache_paths(cache_dir, surface, config, backend):
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
        operator = PatchOperator.load(path, key=key)  # as the file holds it, whether built now or read
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
    pairs, lam = fit_pairs(index, r, theta, interpolation, config)
    return PatchOperator(
        pairs=pairs,
        frames=frames,
        patch_sample_index=index,
        patch_radius=r,
        patch_angle=theta,
        interpolation=interpolation,
        config=config,
        lam=lam,
    )


def fit_pairs(index, r, theta, interpolation, config: PatchConfig) -> tuple[VertexPairs, float]:
    """The matrix of patches given by their samples: each patch fitted (:func:`fit_groups`) and carried to
    the vertices through the interpolation (:func:`carry_to_vertices`).

    Args:
        index, r, theta: (N, n) sample ids (-1 for padding), normalised radii and angles, nearest first.
        interpolation: (M, N) CSR.
        config: :class:`PatchConfig` (degree, ridge, ``subtract_center``).

    Returns:
        ``(pairs, lam)``: the float64 :class:`VertexPairs` and the absolute ridge λ used.
    """
    counts = (index >= 0).sum(axis=1)
    groups, lam = fit_groups(r, theta, counts, config.n_max, config.ridge)
    return carry_to_vertices(groups, index, interpolation, config.k, config.subtract_center), lam


def padded_patches(indptr, samples, r, theta, n_vertices: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The flat patch lists (``indptr`` (N+1,), ``samples``, ``r``, ``theta`` (P,)) as ``(index, r, theta)``,
    each (N, n): int64 sample ids padded with -1, float64 radii and angles padded with 0."""
    indptr = np.asarray(indptr, dtype=np.int64)
    counts = np.diff(indptr)
    width = max(int(counts.max(initial=0)), 1)
    rows = np.repeat(np.arange(n_vertices), counts)
    rank = np.arange(len(rows)) - indptr[rows]
    index = np.full((n_vertices, width), -1, dtype=np.int64)
    r_padded, theta_padded = np.zeros((n_vertices, width)), np.zeros((n_vertices, width))
    index[rows, rank] = samples
    r_padded[rows, rank] = r
    theta_padded[rows, rank] = theta
    return index, r_padded, theta_padded
