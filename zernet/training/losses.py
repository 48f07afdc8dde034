"""Training losses, in the trained units of :mod:`zernet.inference.targets`."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from zernet.inference.targets import unstandardise
from zernet.training.config import ConfigError

__all__ = ["resolve_loss", "compute_loss", "check_loss_targets"]


def resolve_loss(loss: str, task: str) -> str:
    """The loss ``train.loss`` means for ``task``: ``auto`` is cross-entropy or MSE; a loss that does not fit
    the task is a :class:`ConfigError`."""
    if loss == "auto":
        return "cross_entropy" if task == "classification" else "mse"
    if task == "classification" and loss != "cross_entropy":
        raise ConfigError(f"train.loss {loss!r} does not fit a classification task (use cross_entropy)")
    if task == "regression" and loss == "cross_entropy":
        raise ConfigError("train.loss cross_entropy does not fit a regression task (use mse, l1 or relative_l1)")
    return loss


def compute_loss(
    name: str,
    output: torch.Tensor,
    target: torch.Tensor,
    target_stats: dict | None = None,
    soft_labels: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> torch.Tensor:
    """Training loss; ``output`` and ``target`` are in the trained units (see
    :func:`zernet.inference.targets.standardise`).

    ``soft_labels`` (cross-entropy only): ``(indices, weights)``, each (C, K), from
    :func:`zernet.inference.template_graph.geodesic_soft_labels`; a vertex of class ``t`` is scored against the
    distribution that puts ``weights[t, k]`` on class ``indices[t, k]`` instead of all on ``t``.

    ``relative_l1`` is the mean of ``|ŷ - y| / |y|`` in the target's own units, i.e. the MAPE the regression
    is scored with. Its minimiser is not the median that ``l1`` estimates: where a vertex's value is
    uncertain (e.g. near a cut boundary) it predicts lower, because over-predicting a small value costs
    more relative error than under-predicting it by the same factor.
    """
    if name == "cross_entropy" and soft_labels is not None:
        indices, weights = (table.to(output.device) for table in soft_labels)
        log_probabilities = F.log_softmax(output, dim=1).gather(1, indices[target])
        return -(weights[target] * log_probabilities).sum(dim=1).mean()
    if name == "cross_entropy":
        return F.cross_entropy(output, target)
    output = output.reshape(target.shape)
    if name == "mse":
        return F.mse_loss(output, target)
    if name == "l1":
        return F.l1_loss(output, target)
    std = 1.0 if target_stats is None else target_stats["std"]
    if target_stats is not None and target_stats.get("transform", "none") == "log":
        # ŷ / y = exp(std (o - t)): no exp of the values themselves, so no overflow early in training
        return torch.expm1((output - target) * std).abs().mean()
    true = unstandardise(target, target_stats)
    return ((output - target).abs() * std / true.abs()).mean()


def check_loss_targets(name: str, dataset, indices: Sequence[int]) -> None:
    """``relative_l1`` divides by the target: refuse a zero target, naming the shape and the vertex."""
    if name != "relative_l1":
        return
    for i in indices:
        target = np.asarray(dataset.target(i)).ravel()
        if not np.all(target != 0):
            bad = int(np.flatnonzero(target == 0)[0])
            raise ConfigError(
                f"train.loss relative_l1 divides by the target, but shape {dataset.names[i]} has 0 at vertex {bad}"
            )
