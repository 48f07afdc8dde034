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
``zernet_patch{s}_value``   ``(P, k)`` f16   ``value[i, j] = A[p_i k + j, q_i]``: the operator matrix ``A``
                                             (:class:`~zernet.operators.PatchOperator`), in the precision the
                                             operator cache holds it (``PatchConfig.precision``, float16 by
                                             default)
``zernet_patch{s}_frames``  ``(N, 3, 3)``    the tangent frames (rows e1, e2, normal), float64: what the
                                             direction-preserving model's transport angles are computed from
=========================== ================ ===================================================================

The pairs and their ``k`` values are the operator's own compact form (:mod:`zernet.operators.pairs`),
the one the operator cache holds, so a ``Data`` holds what a cached operator holds. A batch's pairs are
the surfaces' pairs offset by PyG, i.e. the block-diagonal operator :meth:`Geometry.concatenate
<zernet.operators.Geometry.concatenate>` builds. :class:`PairOperator` multiplies by them as
:class:`~zernet.operators.PatchOperator` does: on the CPU its products read the pairs (the backward's
order of the pairs is one counting pass per batch), on a GPU it expands them there for each product.

Not covered: ``paper-zernet`` re-solves its fit from the patch samples, which a ``Data`` does not carry (use
zernet's own data pipeline for it).
"""

from __future__ import annotations

import os

import numpy as np
import scipy.sparse as sp
import torch
from torch import Tensor
from torch_geometric.data import Data
from torch_geometric.transforms import BaseTransform

from zernet.data.preprocess import as_patch_configs, prepare_record
from zernet.geometry import Surface
from zernet.operators import Geometry, SparseApply, basis_orders_of_size, checked_basis_order
from zernet.operators.pairs import PairApply, VertexPairs, expanded_csr, narrow_index_dtype, narrow_indptr
from zernet.operators.sparse import canonical_device
from zernet.zernike import n_max_for

__all__ = ["ZernetOperators", "geometry_from_pyg", "PairOperator", "operator_keys"]


# The stored precision of a value dtype (:data:`zernet.operators.pairs.PRECISIONS`).
_PRECISION_OF = {
    torch.float64: "float64",
    torch.float32: "float32",
    torch.float16: "float16",
    torch.bfloat16: "bfloat16",
}


def operator_keys(scale: int) -> tuple[str, str, str]:
    """The ``Data`` attribute names of patch scale ``scale``: ``(index, value, frames)``."""
    return f"zernet_patch{scale}_index", f"zernet_patch{scale}_value", f"zernet_patch{scale}_frames"


# ====================================================================== the operator
class PairOperator:
    """A patch operator stored as vertex pairs and ``k`` values per pair, on any device.

    It has the interface layers and :class:`~zernet.operators.Geometry` use (``apply``, ``k``, ``n_max``,
    ``n_vertices``, ``to``, ``concatenate``; ``matrix`` and ``frames`` for the directional operators), like
    :class:`~zernet.operators.PatchOperator`, whose compact form it holds as tensors
    (:class:`~zernet.operators.pairs.VertexPairs`): on the CPU its products read the pairs
    (:class:`~zernet.operators.pairs.PairApply`), elsewhere they are expanded on that device
    (:func:`~zernet.operators.pairs.expanded_csr`).

    Args:
        index: ``(2, P)`` int64 pairs ``(p, q)``, sorted by ``(p, q)``, no repeats (they are sorted if not).
        value: ``(P, k)`` ``value[i, j] = A[p_i k + j, q_i]``, float64, float32, float16 or bfloat16.
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
        if value.dtype not in _PRECISION_OF:
            raise ValueError(f"PairOperator values must be one of {list(_PRECISION_OF)}, got {value.dtype}")
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
        self._device_arrays: dict[torch.device, dict[str, Tensor]] = {}  # the pairs' tensors off the CPU
        self._host: dict[str, object] = {}

    @classmethod
    def from_operator(cls, operator) -> PairOperator:
        """The pairs, values (in the precision its cache stores them, ``config.precision``) and frames
        (float64) of a :class:`~zernet.operators.PatchOperator`."""
        pairs = operator.pairs.with_precision(operator.config.precision)
        rows = np.repeat(np.arange(pairs.n_vertices, dtype=np.int64), np.diff(pairs.indptr.astype(np.int64)))
        index = torch.from_numpy(np.stack([rows, pairs.columns.astype(np.int64)]))
        frames = getattr(operator, "frames", None)
        frames = None if frames is None else torch.tensor(np.asarray(frames, dtype=np.float64))
        return cls(index, pairs.torch_arrays()["values"], pairs.n_vertices, frames)

    def __repr__(self) -> str:
        return f"PairOperator(N={self.n_vertices}, k={self.k}, pairs={self.index.shape[1]}, device={self.index.device})"

    @property
    def nnz(self) -> int:
        """Stored entries of the matrix (``P k``, explicit zeros included)."""
        return int(self.value.numel())

    # ------------------------------------------------------------------ products
    def _pairs(self) -> VertexPairs:
        """The pairs on the host as :class:`~zernet.operators.pairs.VertexPairs`, built once."""
        if "pairs" not in self._host:
            index = self.index.cpu().numpy()
            indptr = np.zeros(self.n_vertices + 1, dtype=np.int64)
            np.cumsum(np.bincount(index[0], minlength=self.n_vertices), out=indptr[1:])
            value = self.value.detach().cpu()
            precision = _PRECISION_OF[value.dtype]
            values = value.view(torch.int16).numpy().view(np.uint16) if precision == "bfloat16" else value.numpy()
            columns = index[1].astype(narrow_index_dtype(max(self.n_vertices - 1, 0)))
            self._host["pairs"] = VertexPairs(narrow_indptr(indptr), columns, np.ascontiguousarray(values), precision)
        return self._host["pairs"]

    def apply(self, x: Tensor, basis_order: tuple | None = None) -> Tensor:
        """``x`` ``(N,)`` or ``(N, *C)`` -> Zernike coefficients ``(N, k)`` or ``(N, k, *C)``, in ``x``'s dtype and
        device, differentiable; ``basis_order`` as :meth:`zernet.operators.PatchOperator.apply`."""
        if x.shape[0] != self.n_vertices:
            raise ValueError(f"features have {x.shape[0]} rows but the operator has {self.n_vertices} vertices")
        trailing = x.shape[1:]
        flat = x.reshape(self.n_vertices, -1)
        order = checked_basis_order(basis_order, self.k) or tuple(range(self.k))
        if x.device.type == "cpu":
            compute = x.dtype if x.dtype in (torch.float32, torch.float64) else torch.float32
            order_array = np.asarray(order, dtype=np.int64)
            out = PairApply.apply(flat.to(compute).contiguous(), [self._pairs()], order_array).to(x.dtype)
        else:
            device = canonical_device(x.device)
            if device not in self._device_arrays:
                self._device_arrays[device] = {n: t.to(device) for n, t in self._pairs().torch_arrays().items()}
            needs_transpose = torch.is_grad_enabled() and flat.requires_grad  # only the backward reads Aᵀ
            arrays = self._device_arrays[device]
            matrix, transpose = expanded_csr(arrays, self.k, self.n_vertices, x.dtype, order, needs_transpose)
            out = SparseApply.apply(flat.contiguous(), matrix, transpose)
        return out.reshape((self.n_vertices, self.k) + tuple(trailing))

    __call__ = apply

    def to(self, device, basis_orders=()) -> PairOperator:
        """Move the tensors to ``device`` and prepare the pairs there (as :meth:`zernet.operators.PatchOperator.to`;
        a basis order needs nothing prepared); returns ``self``."""
        device = canonical_device(device)
        basis_orders_of_size(basis_orders, self.k)  # checked
        if self.index.device != device:
            self.index, self.value = self.index.to(device), self.value.to(device)
            self.frames_tensor = None if self.frames_tensor is None else self.frames_tensor.to(device)
        if device.type != "cpu" and device not in self._device_arrays:
            self._device_arrays = {device: {n: t.to(device) for n, t in self._pairs().torch_arrays().items()}}
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
        """``A`` ``(N k, N)`` (row ``p k + j``) as a scipy CSR matrix, sorted indices, float32 (float64 values
        stay float64); built from the pairs on every access."""
        return self._pairs().to_csr()

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
