"""One training epoch and one validation pass (each reading the next step's shapes ahead).

Shapes come from a :class:`~zernet.training.residency.ShapeStore`: held on the device, held in host memory
and copied ahead, or read from the cache for every step (``data.residency``)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from tqdm.auto import tqdm

from zernet import metrics as zmetrics
from zernet.distributed import DistributedContext
from zernet.inference.batch import Batch, model_basis_orders, model_directional_order
from zernet.inference.runtime import precision_autocast
from zernet.inference.targets import unstandardise
from zernet.threads import prefetched
from zernet.training.augment import augment_records
from zernet.training.config import TrainSection
from zernet.training.losses import compute_loss
from zernet.training.schedule import epoch_learning_rate, epoch_order, step_groups

__all__ = ["Objective", "train_one_epoch", "validate"]


@dataclass(frozen=True)
class Objective:
    """What the model learns and how its outputs are read: the task, the loss and the scaling statistics."""

    task: str  # classification | regression
    loss: str  # see zernet.training.losses.resolve_loss
    target_stats: dict | None
    feature_stats: dict | None
    # Correspondence with train.label_radius: (indices, weights), each (C, K), on the run's device.
    soft_labels: tuple[torch.Tensor, torch.Tensor] | None = None


def train_one_epoch(
    net: torch.nn.Module,
    model: torch.nn.Module,
    optimizer: torch.optim.Optimizer,
    shapes,
    train_idx: Sequence[int],
    epoch: int,
    train: TrainSection,
    objective: Objective,
    ctx: DistributedContext,
    progress: bool,
) -> dict:
    """Run the optimiser steps of ``epoch`` over the training shapes; returns its history entry so far
    (``epoch``, ``train_loss`` and, for classification, ``train_accuracy``), summed over the ranks.

    ``net`` is what the forward pass goes through (DistributedDataParallel in a distributed run),
    ``model`` the module itself (its parameters are clipped); ``shapes`` the run's
    :class:`~zernet.training.residency.ShapeStore`, or the data set itself (its records as it gives them).
    """
    dataset = getattr(shapes, "dataset", shapes)
    device = ctx.device
    net.train()
    ctx.seed_epoch(train.seed, epoch)  # distributed only: per-rank dropout, exact resume
    for group in optimizer.param_groups:  # a function of the epoch alone: resuming needs no state
        group["lr"] = epoch_learning_rate(train, epoch)
    # One process: the whole permutation. Rank r of W: its equal share order[r::W] (padded, see
    # zernet.distributed.shard_indices), so every rank runs the same number of steps.
    order = ctx.shard([train_idx[i] for i in epoch_order(train.seed, epoch, len(train_idx))])
    groups = step_groups(order, train.shapes_per_step)
    classification = objective.task == "classification"
    loss_sum, hit_sum, vertex_sum = 0.0, 0.0, 0
    directional = model_directional_order(net)
    basis_orders = model_basis_orders(net)

    def step_batch(numbered_group):
        step, group = numbered_group
        records = augment_records(
            [shapes[i] for i in group],
            train,
            dataset.feature_kind,
            [c.n_max for c in dataset.patch_configs],
            epoch,
            step,
            directional,
        )
        return Batch(records, device, objective.target_stats, objective.feature_stats, directional, basis_orders)

    # The next step's shapes are read (or copied to the device) while this step computes.
    batches = prefetched(step_batch, enumerate(groups, start=1))
    bar = tqdm(
        batches,
        total=len(groups),
        desc=f"epoch {epoch}/{train.epochs}",
        unit="step",
        leave=False,
        disable=not progress,
        dynamic_ncols=True,
    )
    for step, batch in enumerate(bar, start=1):
        optimizer.zero_grad(set_to_none=True)
        with precision_autocast(train.precision, device.type):
            output = net(batch.features, batch.geometry)
        output = output.float()  # the loss in float32
        loss = compute_loss(objective.loss, output, batch.target, objective.target_stats, objective.soft_labels)
        if not torch.isfinite(loss):
            raise FloatingPointError(
                f"the training loss became {loss.item()} at epoch {epoch}, step {step} (shapes "
                f"{', '.join(batch.names)}); lower train.lr or check the targets for NaN/inf"
            )
        loss.backward()
        if train.grad_clip:
            torch.nn.utils.clip_grad_norm_(model.parameters(), train.grad_clip)
        optimizer.step()
        n = int(batch.target.shape[0])
        loss_sum += loss.item() * n
        vertex_sum += n
        postfix = {"loss": f"{loss_sum / vertex_sum:.4g}"}
        if classification:
            hit_sum += (output.detach().argmax(dim=1) == batch.target).sum().item()
            postfix["acc"] = f"{hit_sum / vertex_sum:.3f}"
        bar.set_postfix(postfix)
    bar.close()
    loss_sum, hit_sum, vertex_sum = ctx.sum_over_ranks(loss_sum, hit_sum, vertex_sum)
    entry = {"epoch": epoch, "train_loss": loss_sum / vertex_sum}
    if classification:
        entry["train_accuracy"] = hit_sum / vertex_sum
    return entry


@torch.no_grad()
def validate(
    model: torch.nn.Module, shapes, indices: Sequence[int], device: torch.device, objective: Objective
) -> dict:
    """Mean validation loss and metric (accuracy, or MAPE for regression) over shapes, each counting once
    (``shapes``: a :class:`~zernet.training.residency.ShapeStore`, or any sequence of records)."""
    model.eval()
    losses, scores = [], []
    directional = model_directional_order(model)
    basis_orders = model_basis_orders(model)

    def shape_batch(i):
        record = shapes[i]
        return record, Batch(
            [record], device, objective.target_stats, objective.feature_stats, directional, basis_orders
        )

    for record, batch in prefetched(shape_batch, indices):
        output = model(batch.features, batch.geometry)
        losses.append(
            compute_loss(objective.loss, output, batch.target, objective.target_stats, objective.soft_labels).item()
        )
        if objective.task == "classification":
            scores.append(zmetrics.accuracy(output.argmax(dim=1), batch.target))
        else:
            pred = unstandardise(output.reshape(-1), objective.target_stats)
            scores.append(zmetrics.regression_scores(pred, record.target)["MAPE"])
    model.train()
    key = "val_accuracy" if objective.task == "classification" else "val_MAPE"
    return {"val_loss": float(np.mean(losses)), key: float(np.mean(scores))}
