"""One forward pass's input: the features, targets and geometry of one or more concatenated surfaces."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from zernet.inference.targets import standardise, standardise_features
from zernet.operators import Geometry

__all__ = ["Batch", "with_directional", "model_directional_order", "model_basis_orders"]


def model_directional_order(model: torch.nn.Module) -> int | None:
    """Fourier order of the directional operators ``model`` reads (None: it needs none); sees through a
    DistributedDataParallel wrapper."""
    return getattr(getattr(model, "module", model), "directional_order", None)


def model_basis_orders(model: torch.nn.Module) -> tuple[tuple, ...]:
    """The basis orders the model's convolutions ask of the patch operators
    (:meth:`zernet.nn.ZernikeConv.operator_basis_order`), each once; empty when all read the natural order."""
    orders = []
    for module in model.modules():
        order = module.operator_basis_order() if hasattr(module, "operator_basis_order") else None
        if order is not None and order not in orders:
            orders.append(order)
    return tuple(orders)


def with_directional(record, order: int | None) -> Geometry:
    """The record's geometry with directional operators of ``order`` (built before the network, never in
    its forward). Kept on the record, so a data set held in memory builds them once per shape."""
    if order is None:
        return record.geometry
    geometry = record.geometry.with_directional(order)
    if geometry is not record.geometry:
        record.geometry = geometry
    return geometry


class Batch:
    """Features (standardised with ``feature_stats`` if given), targets (in trained units with
    ``target_stats`` if given) and geometry of ``records``, on ``device``; the patch operators hold their
    matrices in ``basis_orders`` (:func:`model_basis_orders`), so building a batch on the read-ahead
    thread leaves no operator work to the forward pass."""

    def __init__(
        self,
        records: Sequence,
        device: torch.device,
        target_stats: dict | None = None,
        feature_stats: dict | None = None,
        directional_order: int | None = None,
        basis_orders: Sequence[tuple] = (),
    ):
        self.names = [r.name for r in records]
        self.sizes = [len(r.features) for r in records]
        self.features = torch.from_numpy(np.concatenate([np.asarray(r.features, np.float32) for r in records]))
        self.features = self.features.to(device)
        if feature_stats is not None:
            self.features = standardise_features(self.features, feature_stats)
        geometries = [with_directional(r, directional_order) for r in records]
        geometry = geometries[0] if len(geometries) == 1 else Geometry.concatenate(geometries)
        self.geometry = geometry.to(device, basis_orders)
        self.target = None
        if records[0].target is not None:
            target = np.concatenate([np.asarray(r.target) for r in records])
            self.target = torch.from_numpy(target).to(device)
            if target_stats is not None:  # regression on (log-)standardised targets
                self.target = standardise(self.target, target_stats)
