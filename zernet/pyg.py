"""PyTorch Geometric interop: zernet's patch operators on PyG ``Data`` objects, zernet's models on PyG batches.

Two pieces, and one way to use them:

- :class:`ZernetOperators`, a ``torch_geometric.transforms.BaseTransform``: builds (and caches, through
  :func:`~zernet.operators.build_patch_operator`'s ``cache_dir``) the patch operators of a ``Data`` with
  ``pos`` and ``face`` (PyG's ``(3, F)`` layout) or ``pos`` only (a point cloud), by the same steps as a
  zernet data set shape (:func:`zernet.data.preprocess.prepare_record`: validated, optionally scaled to
  ``area``, a cloud triangulated through its own points), and attaches them to the ``Data`` as tensors,
  with zernet's input features as ``x``. Use it as the ``pre_transform`` of any PyG data set.
- :func:`geometry_from_pyg` turns a ``Data`` or a ``Batch`` carrying them into zernet's
  :class:`~zernet.operators.Geometry`. Every zernet model then runs on PyG objects as::

      out = model(batch.x, geometry_from_pyg(batch, model.directional_order))   # (num_nodes, C_out)

  and a layer as ``conv(batch.x, geometry_from_pyg(batch).operators[0])``.

What a ``Data`` carries, per patch scale ``s`` (plain tensors, so PyG's collate, ``InMemoryDataset.save`` /
``load`` (``torch.load(weights_only=True)``) and ``Data.to(device)`` handle them with no custom class):

=========================== ================ ===================================================================
attribute                   shape, dtype     meaning
=========================== ================ ===================================================================
``zernet_patch{s}_index``   ``(2, P)`` int64 the vertex pairs ``(p, q)`` that share a patch (``q`` in ``p``'s
                                             patch), sorted; ``index`` in the name makes PyG offset both rows
                                             by the vertices before them when it batches, as for ``edge_index``
``zernet_patch{s}_value``   ``(P, k)`` f32   ``value[i, j] = A[p_i k + j, q_i]``: the operator matrix ``A``
                                             (:class:`~zernet.operators.PatchOperator`), float32 as the
                                             operator cache and the layers hold it
``zernet_patch{s}_frames``  ``(N, 3, 3)``    the tangent frames (rows e1, e2, normal), float64: what the
                                             direction-preserving model's transport angles are computed from
=========================== ================ ===================================================================

The pairs and their ``k`` values are the matrix with its ``k`` rows per vertex side by side (a patch fit's rows
of one vertex read the same vertices), so a ``Data`` holds less than the operator cache's matrix and
transpose. A batch's pairs are the surfaces' pairs offset by PyG, i.e. the block-diagonal operator
:meth:`Geometry.concatenate <zernet.operators.Geometry.concatenate>` builds. :class:`PairOperator` builds its
torch CSR matrix and transpose (in each basis order the layers ask for) from them on the batch's device,
once per batch: copies of the arrays and one sort of the ``P`` pairs, no sort of the matrix. At FAUST size
(6,890 vertices, 376 k pairs, k = 21) that took 0.3-0.5 s at one CPU thread on a loaded 2-core machine,
about 2.5x what zernet's own pipeline spends preparing a cached operator for a step (which, with its
operators held in memory, it does once per shape, not per step).

Not covered: ``paper-zernet`` re-solves its fit from the patch samples, which a ``Data`` does not carry (use
zernet's own data pipeline for it).
"""

from __future__ import annotations

import os
import warnings

import numpy as np
import scipy.sparse as sp
import torch
from torch import Tensor
from torch_geometric.data import Data
from torch_geometric.transforms import BaseTransform

from zernet.data.preprocess import as_patch_configs, prepare_record
from zernet.geometry import Surface
from zernet.operators import Geometry, basis_orders_of_size, checked_basis_order
from zernet.operators.directional import patch_pairs
from zernet.operators.sparse import canonical_device, csr_transpose
from zernet.zernike import n_max_for

__all__ = ["ZernetOperators", "geometry_from_pyg", "PairOperator", "operator_keys"]


def operator_keys(scale: int) -> tuple[str, str, str]:
    """The ``Data`` attribute names of patch scale ``scale``: ``(index, value, frames)``."""
    return f"zernet_patch{scale}_index", f"zernet_patch{scale}_value", f"zernet_patch{scale}_frames"


# ====================================================================== the operator
class _PairApply(torch.autograd.Function):
    """``y = A x`` in the layout of :meth:`PairOperator.apply` (row ``p k + j``) from ``A``'s rows ordered by basis
    (row ``j N + p``), and ``grad_x = Aᵀ g`` with the stored transpose (as :class:`zernet.operators.SparseApply`)."""

    @staticmethod
    def forward(ctx, x, by_basis, transpose, k):
        ctx.transpose = transpose
        n = x.shape[0]
        return (by_basis @ x).view(k, n, -1).transpose(0, 1).reshape(n * k, -1)

    @staticmethod
    def backward(ctx, grad):
        if not ctx.needs_input_grad[0]:
            return None, None, None, None
        return ctx.transpose @ grad.contiguous(), None, None, None


class PairOperator:
    """A patch operator stored as vertex pairs and ``k`` values per pair, on any device.

    It has the interface layers and :class:`~zernet.operators.Geometry` use (``apply``, ``k``, ``n_max``,
    ``n_vertices``, ``to``, ``concatenate``; ``matrix`` and ``frames`` for the directional operators), like
    :class:`zernet.nn.reference.MatrixOperator`, but keeps its arrays as torch tensors: a batch on the GPU
    builds its matrices there.

    Args:
        index: ``(2, P)`` int64 pairs ``(p, q)``, sorted by ``(p, q)``, no repeats (they are sorted if not).
        value: ``(P, k)`` ``value[i, j] = A[p_i k + j, q_i]``.
        n_vertices: ``N``.
        frames: optional ``(N, 3, 3)`` tangent frames (rows e1, e2, normal).
    """

    accepts_basis_order = True  # as PatchOperator.apply
    cache_file = None  # no cache file: directional operators compute their transport angles

    def __init__(self, index: Tensor, value: Tensor, n_vertices: int, frames: Tensor | None = None):
        n_vertices = int(n_vertices)
        if index.dim() != 2 or index.shape[0] != 2 or value.dim() != 2 or value.shape[0] != index.shape[1]:
            raise ValueError(
                f"PairOperator needs index (2, P) and value (P, k), got {tuple(index.shape)} and {tuple(value.shape)}"
            )
        index = index.long()
        if index.numel() and (int(index.min()) < 0 or int(index.max()) >= n_vertices):
            raise ValueError(f"PairOperator: pair indices must lie in [0, {n_vertices})")
        key = index[0] * n_vertices + index[1]
        if key.numel() > 1 and not bool((key[1:] > key[:-1]).all()):
            key, order = torch.sort(key)
            if bool((key[1:] == key[:-1]).any()):
                raise ValueError("PairOperator: a vertex pair appears twice")
            index, value = index[:, order], value[order]
        if frames is not None and tuple(frames.shape) != (n_vertices, 3, 3):
            raise ValueError(f"PairOperator: frames must be ({n_vertices}, 3, 3), got {tuple(frames.shape)}")
        self.index, self.value, self.frames_tensor = index, value, frames
        self.n_vertices = n_vertices
        self.k = int(value.shape[1])
        self.n_max = n_max_for(self.k)
        self._tensors: dict[tuple, tuple[Tensor, Tensor]] = {}  # (dtype, device, basis order) -> (A, Aᵀ)
        self._host: dict[str, object] = {}

    @classmethod
    def from_operator(cls, operator) -> PairOperator:
        """The pairs, values (float32) and frames (float64) of a :class:`~zernet.operators.PatchOperator`
        (or any operator with a CSR ``matrix``, ``k`` and ``frames``)."""
        matrix = sp.csr_matrix(operator.matrix)
        if not matrix.has_sorted_indices:
            matrix = matrix.copy()
            matrix.sort_indices()
        k, n = int(operator.k), int(operator.n_vertices)
        pairs = patch_pairs(matrix, k)
        rows = np.repeat(np.arange(matrix.shape[0], dtype=np.int64), np.diff(matrix.indptr))
        entry = np.searchsorted(pairs[:, 0] * n + pairs[:, 1], (rows // k) * n + matrix.indices)
        value = np.zeros((len(pairs), k), dtype=np.float32)
        value[entry, rows % k] = matrix.data
        frames = getattr(operator, "frames", None)
        frames = None if frames is None else torch.tensor(np.asarray(frames, dtype=np.float64))
        return cls(torch.from_numpy(np.ascontiguousarray(pairs.T)), torch.from_numpy(value), n, frames)

    def __repr__(self) -> str:
        return f"PairOperator(N={self.n_vertices}, k={self.k}, pairs={self.index.shape[1]}, device={self.index.device})"

    @property
    def nnz(self) -> int:
        """Stored entries of the matrix (``P k``, explicit zeros included)."""
        return int(self.value.numel())

    # ------------------------------------------------------------------ matrices
    def _torch_matrices(self, dtype: torch.dtype, device, basis_order: tuple | None = None) -> tuple[Tensor, Tensor]:
        """Torch CSR matrices on ``device``, built on first use and kept: ``A`` with its rows ordered by basis
        first, ``(N k, N)`` with row ``i N + p`` the coefficient ``basis_order[i]`` of vertex ``p`` (every basis
        reads the pairs in their stored order: copies of the arrays, no scatter), and ``Aᵀ`` ``(N, N k)`` with
        the columns of :meth:`zernet.operators.PatchOperator.apply`'s layout, ``p k + i`` (one sort of the
        ``P`` pairs by column)."""
        device = canonical_device(device)
        key = (dtype, device, basis_order)
        if key in self._tensors:
            return self._tensors[key]
        index, value = self.index.to(device), self.value.to(device=device, dtype=dtype)
        n, k, n_pairs = self.n_vertices, self.k, index.shape[1]
        bases = torch.arange(k, device=device) if basis_order is None else torch.tensor(basis_order, device=device)
        index_dtype = torch.int32 if max(n_pairs * k, n * k) < 2**31 - 1 else torch.int64
        p, q = index[0], index[1]
        per_basis = torch.zeros(n + 1, dtype=index_dtype, device=device)
        per_basis[1:] = torch.cumsum(torch.bincount(p, minlength=n), 0)
        crow = torch.cat(
            [
                per_basis[:1],
                (
                    per_basis[1:].unsqueeze(0)
                    + n_pairs * torch.arange(k, dtype=index_dtype, device=device).unsqueeze(1)
                ).reshape(-1),
            ]
        )
        by_column = torch.argsort(q * n + p)  # Aᵀ: row q holds its pairs by p, each with its k columns in order
        t_crow = torch.zeros(n + 1, dtype=index_dtype, device=device)
        t_crow[1:] = torch.cumsum(torch.bincount(q, minlength=n) * k, 0)
        t_columns = (
            p[by_column].to(index_dtype).unsqueeze(1) * k
            + torch.arange(k, dtype=index_dtype, device=device).unsqueeze(0)
        ).reshape(-1)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # "sparse CSR support is in beta"
            by_basis = torch.sparse_csr_tensor(
                crow, q.to(index_dtype).repeat(k), value.t()[bases].reshape(-1), size=(n * k, n), check_invariants=False
            )
            transpose = torch.sparse_csr_tensor(
                t_crow,
                t_columns,
                value[by_column.unsqueeze(1), bases].reshape(-1),
                size=(n, n * k),
                check_invariants=False,
            )
        self._tensors[key] = (by_basis, transpose)
        return by_basis, transpose

    def apply(self, x: Tensor, basis_order: tuple | None = None) -> Tensor:
        """``x`` ``(N,)`` or ``(N, *C)`` -> Zernike coefficients ``(N, k)`` or ``(N, k, *C)``, in ``x``'s dtype and
        device, differentiable; ``basis_order`` as :meth:`zernet.operators.PatchOperator.apply`."""
        if x.shape[0] != self.n_vertices:
            raise ValueError(f"features have {x.shape[0]} rows but the operator has {self.n_vertices} vertices")
        trailing = x.shape[1:]
        flat = x.reshape(self.n_vertices, -1)
        by_basis, transpose = self._torch_matrices(x.dtype, x.device, checked_basis_order(basis_order, self.k))
        out = _PairApply.apply(flat.contiguous(), by_basis, transpose, self.k)
        return out.reshape((self.n_vertices, self.k) + tuple(trailing))

    __call__ = apply

    def to(self, device, basis_orders=()) -> PairOperator:
        """Move the tensors to ``device`` and build the float32 matrices of ``basis_orders`` there (as
        :meth:`zernet.operators.PatchOperator.to`); returns ``self``."""
        device = canonical_device(device)
        if self.index.device != device:
            self.index, self.value = self.index.to(device), self.value.to(device)
            self.frames_tensor = None if self.frames_tensor is None else self.frames_tensor.to(device)
            self._tensors = {key: m for key, m in self._tensors.items() if key[1] == device}
        for order in basis_orders_of_size(basis_orders, self.k):
            self._torch_matrices(torch.float32, device, order)
        return self

    @staticmethod
    def concatenate(ops) -> PairOperator:
        """Block-diagonal operator of several surfaces (vertices stacked in order), on the first one's device."""
        ops = list(ops)
        if not ops:
            raise ValueError("concatenate needs at least one operator")
        if len({op.k for op in ops}) != 1:
            raise ValueError(f"cannot concatenate operators with different k: {[op.k for op in ops]}")
        device = ops[0].index.device
        offsets = np.cumsum([0] + [op.n_vertices for op in ops])[:-1]
        index = torch.cat([op.index.to(device) + int(offset) for op, offset in zip(ops, offsets)], dim=1)
        value = torch.cat([op.value.to(device) for op in ops])
        frames = None
        if all(op.frames_tensor is not None for op in ops):
            frames = torch.cat([op.frames_tensor.to(device) for op in ops])
        return PairOperator(index, value, int(sum(op.n_vertices for op in ops)), frames)

    # ------------------------------------------------------------------ host views (directional operators)
    @property
    def matrix(self) -> sp.csr_matrix:
        """``A`` ``(N k, N)`` (row ``p k + j``) as a scipy CSR matrix, sorted indices, in the values' dtype; built
        on the host once."""
        if "matrix" not in self._host:
            t = self._torch_matrices(self.value.dtype, "cpu")[1]
            arrays = (t.crow_indices().numpy(), t.col_indices().numpy(), t.values().numpy())
            indptr, indices, data = csr_transpose(*arrays, t.shape[1])
            matrix = sp.csr_matrix((data, indices, indptr), shape=tuple(t.shape[::-1]))
            matrix.has_sorted_indices = True
            self._host["matrix"] = matrix
        return self._host["matrix"]

    @property
    def frames(self) -> np.ndarray | None:
        """``(N, 3, 3)`` float64 tangent frames on the host, or ``None``."""
        if self.frames_tensor is None:
            return None
        if "frames" not in self._host:
            self._host["frames"] = self.frames_tensor.detach().cpu().numpy().astype(np.float64)
        return self._host["frames"]

    _PATCH_DATA = (
        "patch_sample_index",
        "patch_radius",
        "patch_angle",
        "patch_basis",
        "interpolation",
        "lam",
        "config",
        "ridge_weights",
    )

    def __getattr__(self, name):
        if name in PairOperator._PATCH_DATA:
            raise AttributeError(
                f"PairOperator has no {name!r}: a PyG Data carries the patch operator's matrix and "
                "frames only, not its patch samples (the paper-zernet model re-fits from them: "
                "train it with zernet's own data pipeline)"
            )
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")


# ====================================================================== the transform
class ZernetOperators(BaseTransform):
    """Attach zernet's patch operators (and input features) to a PyG ``Data``: a ``pre_transform``.

    Args:
        patch_configs: one :class:`~zernet.operators.PatchConfig` (or dict) per scale, or one of them; the
            single-scale models read the first. An empty list attaches none (a FeaStNet-only data set).
        cache_dir: folder of zernet's operator cache (:func:`~zernet.operators.build_patch_operator`):
            a surface processed again (another data set, ``force_reload``) reads its operators back.
        area: scale each surface to this area before building its operators and features, as zernet's
            data sets do (``patch.area``; 15000 for FAUST with ``r0 = 5.5``); ``None`` keeps the size.
            ``pos`` itself is left as it is.
        features: a zernet feature kind (``"xyz"``, ``"xyz+normals"``, ``"shape+curvature"``, ...,
            :func:`zernet.data.features.compute_features`) written to ``data.x`` as float32 (replacing
            any ``x``), or ``None`` to leave ``x`` alone.

    The ``Data`` needs ``pos`` ``(N, 3)``, and ``face`` ``(3, F)`` for a mesh (without it, the points are a
    cloud, triangulated through its own points); a ``normal`` ``(N, 3)`` attribute is taken as given
    normals. Surfaces are validated but never repaired (a repair would renumber the vertices): a mesh
    with duplicate vertices or zero-area faces raises :class:`~zernet.geometry.SurfaceError`.
    Attaches the tensors listed in :mod:`zernet.pyg` for every scale.
    """

    def __init__(
        self,
        patch_configs,
        cache_dir: str | os.PathLike | None = None,
        area: float | None = None,
        features: str | None = "xyz",
    ):
        self.patch_configs = as_patch_configs(patch_configs)
        self.cache_dir = None if cache_dir is None else str(cache_dir)
        self.area = None if area is None else float(area)
        self.features = features

    def forward(self, data: Data) -> Data:
        if getattr(data, "pos", None) is None:
            raise ValueError("ZernetOperators needs data.pos (N, 3): the vertices of a mesh or the points of a cloud")
        face = getattr(data, "face", None)
        normal = getattr(data, "normal", None)
        surface = Surface(
            data.pos.detach().cpu().double().numpy(),
            None if face is None else face.detach().cpu().t().numpy(),
            None if normal is None else normal.detach().cpu().double().numpy(),
            name="<pyg Data>",
        )
        record = prepare_record(
            surface, self.patch_configs, self.cache_dir, self.area, feature_kind=self.features or "ones", name="pyg"
        )
        n = surface.n_vertices
        if record.surface.n_vertices != n:  # cannot happen without repair; guards the alignment with pos
            raise ValueError(f"zernet's preprocessing changed the vertex count ({n} -> {record.surface.n_vertices})")
        for scale, operator in enumerate(record.geometry.operators):
            pairs = PairOperator.from_operator(operator)
            index_key, value_key, frames_key = operator_keys(scale)
            data[index_key], data[value_key] = pairs.index, pairs.value
            if pairs.frames_tensor is not None:
                data[frames_key] = pairs.frames_tensor
        if self.features is not None:
            data.x = torch.from_numpy(np.ascontiguousarray(record.features, dtype=np.float32))
        return data

    def __repr__(self) -> str:
        # InMemoryDataset compares this with the one it processed with; the cache folder changes nothing.
        configs = ", ".join(repr(c) for c in self.patch_configs)
        return f"{type(self).__name__}(patch_configs=[{configs}], area={self.area}, features={self.features!r})"


# ====================================================================== Data -> Geometry
def geometry_from_pyg(data, directional_order: int | None = None) -> Geometry:
    """zernet's :class:`~zernet.operators.Geometry` of a PyG ``Data`` or ``Batch`` prepared by
    :class:`ZernetOperators`: ``model(data.x, geometry_from_pyg(data, model.directional_order))``.

    - ``operators``: one :class:`PairOperator` per scale, on the data's device; a batch's is the
      block-diagonal operator of its surfaces, as :meth:`Geometry.concatenate` builds it.
    - ``edge_index``: ``data.edge_index`` if present, else the mesh edges of ``data.face`` in both
      directions (FeaStNet reads them), else ``None``.
    - ``batch``: ``data.batch`` for a ``Batch`` (the surface of every vertex), else ``None``.
    - ``directional``: built for ``directional_order`` (pass ``model.directional_order``; ``None``: none),
      on the host, as :meth:`Geometry.with_directional`.
    """
    n = int(data.num_nodes)
    operators, scale = [], 0
    while operator_keys(scale)[0] in data:
        index_key, value_key, frames_key = operator_keys(scale)
        frames = data[frames_key] if frames_key in data else None
        operators.append(PairOperator(data[index_key], data[value_key], n, frames))
        scale += 1
    edge_index = getattr(data, "edge_index", None)
    face = getattr(data, "face", None)
    if edge_index is None and face is not None:
        edge_index = face_edges(face)
    if not operators and edge_index is None:
        raise ValueError(
            "this Data has neither zernet's patch operators nor edges: add ZernetOperators(...) as "
            "its data set's pre_transform"
        )
    batch = getattr(data, "batch", None)
    return Geometry(operators, edge_index, batch).with_directional(directional_order)


def face_edges(face: Tensor) -> Tensor:
    """``(2, E)`` int64 edges of the triangles ``face`` ``(3, F)``, each once in each direction."""
    pairs = torch.cat([face[[0, 1]], face[[1, 2]], face[[2, 0]]], dim=1).long()
    pairs = torch.unique(torch.sort(pairs, dim=0).values, dim=1)
    return torch.cat([pairs, pairs.flip(0)], dim=1)
