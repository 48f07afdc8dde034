"""What a model needs to know about one surface, or a batch of surfaces, besides its features.

Every model has the signature ``model(x (N, C_in), geometry: Geometry) -> (N, C_out)``. Zernike models read
``geometry.operators`` (one :class:`~zernet.operators.PatchOperator` per scale); direction-preserving
models also read ``geometry.directional`` (one :class:`~zernet.operators.DirectionalOperator` per scale,
built when the data are prepared with :meth:`Geometry.with_directional`); graph baselines read
``geometry.edge_index``. A batch of several surfaces of different sizes is one block-diagonal
``Geometry`` (:meth:`Geometry.concatenate`): vertices are stacked in order, no patch or edge crosses
surfaces, and ``batch[i]`` names the surface vertex ``i`` belongs to.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import torch

from .directional import DirectionalOperator, build_directional_operator

__all__ = ["Geometry"]


@dataclass
class Geometry:
    """Operators and connectivity of one surface or a block-diagonal batch.

    Attributes:
        operators: patch operators, one per scale (single-scale models use ``operators[0]``); each has
            ``apply(x) -> (N, k, d)``, ``k`` and ``n_vertices``.
        edge_index: ``(2, E)`` int64 mesh edges in both directions, or ``None`` (point clouds).
        batch: ``(N,)`` int64 surface id per vertex for a batch, or ``None`` for a single surface.
        directional: directional operators of one Fourier order, one per scale (``directional[i]`` is
            built from ``operators[i]``), or empty when the geometry was built without them
            (:meth:`with_directional` adds them).
    """

    operators: list = field(default_factory=list)
    edge_index: torch.Tensor | None = None
    batch: torch.Tensor | None = None
    directional: list[DirectionalOperator] = field(default_factory=list)

    @property
    def n_vertices(self) -> int:
        """Number of vertices ``N`` (from the first operator, else ``batch``, else ``edge_index``)."""
        for op in self.operators:
            n = getattr(op, "n_vertices", None)
            if n is not None:
                return int(n)
        if self.batch is not None:
            return int(self.batch.numel())
        if self.edge_index is not None and self.edge_index.numel():
            return int(self.edge_index.max()) + 1
        raise ValueError("Geometry has no operators, batch or edges: its number of vertices is unknown")

    @property
    def num_surfaces(self) -> int:
        """Number of surfaces in the batch (1 without ``batch``)."""
        if self.batch is None or self.batch.numel() == 0:
            return 1
        return int(self.batch.max()) + 1

    @property
    def directional_order(self) -> int | None:
        """Fourier order ``L`` of :attr:`directional`, or ``None`` when it is empty."""
        return self.directional[0].order if self.directional else None

    def with_directional(self, order: int | None) -> Geometry:
        """A copy with the directional operators of Fourier order ``order`` of every scale.

        Called when the data are prepared, with the order the model asks for (``model.directional_order``
        or :func:`zernet.nn.models.directional_order`); ``None`` (a model without directional layers)
        returns the geometry unchanged. Operators already of that order are kept.
        """
        if order is None or self.directional_order == order:
            return self
        return replace(self, directional=[build_directional_operator(op, order) for op in self.operators])

    def to(self, device, basis_orders: Sequence[tuple] = ()) -> Geometry:
        """A copy with tensors (and operators that have ``to``) on ``device``; operators that accept a basis
        order also prepare ``basis_orders`` (:meth:`~zernet.operators.PatchOperator.to`)."""
        ops = [
            (op.to(device, basis_orders) if getattr(op, "accepts_basis_order", False) else op.to(device))
            if hasattr(op, "to")
            else op
            for op in self.operators
        ]
        move = lambda t: None if t is None else t.to(device)  # noqa: E731
        return Geometry(ops, move(self.edge_index), move(self.batch), [op.to(device) for op in self.directional])

    def copy_to(self, device, non_blocking: bool = False) -> Geometry:
        """A copy on ``device`` whose operators' prepared tensors are copied there (``copy_to``), while this
        geometry keeps its own: a record held in host memory, copied to the GPU for one step."""
        move = lambda t: None if t is None else t.to(device, non_blocking=non_blocking)  # noqa: E731
        copies = {
            id(op): op.copy_to(device, non_blocking) if hasattr(op, "copy_to") else op.to(device)
            for op in self.operators
        }
        directional = [
            op.copy_to(device, non_blocking, operator=copies.get(id(op.operator)))  # copied once
            for op in self.directional
        ]
        return Geometry([copies[id(op)] for op in self.operators], move(self.edge_index), move(self.batch), directional)

    def pin_memory(self) -> Geometry:
        """The host tensors of this geometry in page-locked memory (CUDA only): operators in place, the
        edge and batch tensors replaced by pinned copies; returns ``self``."""
        for op in self.operators:
            if hasattr(op, "pin_memory"):
                op.pin_memory()
        pin = lambda t: None if t is None else t.pin_memory()  # noqa: E731
        self.edge_index, self.batch = pin(self.edge_index), pin(self.batch)
        return self

    @staticmethod
    def concatenate(items: Sequence[Geometry]) -> Geometry:
        """Block-diagonal batch of surfaces (which may themselves be batches).

        Operators are concatenated per scale with ``type(op).concatenate`` (directional operators with
        :meth:`DirectionalOperator.concatenate`, on top of the concatenated scalar operator); edge indices
        are offset by the vertices before them; ``batch`` numbers the surfaces ``0..B-1`` in order.

        Raises:
            ValueError: no items, different numbers of scales, edges on some items only, or directional
                operators of different orders (or on some items only).
        """
        items = list(items)
        if not items:
            raise ValueError("Geometry.concatenate needs at least one item")
        n_scales = {len(g.operators) for g in items}
        if len(n_scales) != 1:
            raise ValueError(f"cannot batch geometries with different numbers of operators: {sorted(n_scales)}")
        has_edges = {g.edge_index is not None for g in items}
        if len(has_edges) != 1:
            raise ValueError("cannot batch geometries where only some have edge_index (mesh and point cloud?)")
        orders = {g.directional_order for g in items}
        if len(orders) != 1:
            raise ValueError(f"cannot batch geometries with directional operators of different orders: {orders}")
        operators = []
        for i in range(n_scales.pop()):
            ops = [g.operators[i] for g in items]
            operators.append(type(ops[0]).concatenate(ops))
        directional = [
            DirectionalOperator.concatenate([g.directional[i] for g in items], operators[i])
            for i in range(len(items[0].directional))
        ]
        sizes = [g.n_vertices for g in items]
        device = next((t.device for g in items for t in (g.edge_index, g.batch) if t is not None), None)
        return Geometry(
            operators, _stacked_edges(items, sizes, device), _surface_ids(items, sizes, device), directional
        )


def _stacked_edges(items: Sequence[Geometry], sizes: Sequence[int], device) -> torch.Tensor | None:
    """The items' edge indices offset by the vertices before them (``None`` for point clouds)."""
    if items[0].edge_index is None:
        return None
    parts, offset = [], 0
    for g, n in zip(items, sizes):
        parts.append(g.edge_index.to(device) + offset)
        offset += n
    return torch.cat(parts, dim=1)


def _surface_ids(items: Sequence[Geometry], sizes: Sequence[int], device) -> torch.Tensor:
    """Surface id of every vertex of the batch, numbering the surfaces ``0..B-1`` in order."""
    batches, surface = [], 0
    for g, n in zip(items, sizes):
        if g.batch is None:
            batches.append(torch.full((n,), surface, dtype=torch.int64, device=device))
            surface += 1
        else:
            batches.append(g.batch.to(device) + surface)
            surface += g.num_surfaces
    return torch.cat(batches)
