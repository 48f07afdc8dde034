"""What makes every epoch reproducible: the seeded shape order, the learning rate, and the RNG states.

The order in which the training shapes are visited in epoch ``e`` is a permutation drawn from a *fresh*
generator seeded with ``(train.seed, e)`` (:func:`epoch_order`), so it depends on nothing but the seed and
the epoch: a resumed run or any rank of a distributed run computes the same order without shared state.
The model's initialisation and dropout use torch's global generator, seeded once (:func:`seed_everything`);
its state, with numpy's and Python's, goes into every checkpoint (:func:`rng_state`) so that a resumed run
continues exactly where the last checkpoint left off.
"""

from __future__ import annotations

import math
import random
from collections.abc import Sequence

import numpy as np
import torch

from zernet.training.config import TrainSection

__all__ = ["epoch_learning_rate", "epoch_order", "step_groups", "seed_everything", "rng_state", "set_rng_state"]


def epoch_learning_rate(train: TrainSection, epoch: int) -> float:
    """Learning rate of (1-based) ``epoch``: ``train.lr``, or with ``lr_schedule: cosine`` the half cosine
    from ``lr`` at epoch 1 towards 0 after the last of ``train.lr_schedule_epochs`` (default
    ``train.epochs``); epochs past that span keep the last epoch's rate."""
    lr = float(train.lr)
    if train.lr_schedule == "constant":
        return lr
    span = max(int(train.lr_schedule_epochs or train.epochs), 1)
    return 0.5 * lr * (1.0 + math.cos(math.pi * min(epoch - 1, span - 1) / span))


def epoch_order(seed: int, epoch: int, n: int) -> list[int]:
    """The order of the ``n`` training shapes in ``epoch`` (1-based): a permutation from a generator seeded
    with ``(seed, epoch)`` only, so every process and every resume computes the same order."""
    generator = torch.Generator().manual_seed(int(seed) * 1_000_003 + int(epoch))
    return torch.randperm(n, generator=generator).tolist()


def step_groups(order: Sequence[int], shapes_per_step: int) -> list[list[int]]:
    """Cut an epoch's order into optimiser steps of ``shapes_per_step`` shapes (the last one may be short)."""
    return [list(order[i : i + shapes_per_step]) for i in range(0, len(order), shapes_per_step)]


def seed_everything(seed: int) -> None:
    """Seed Python's, numpy's and torch's global generators."""
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def rng_state() -> dict:
    """torch, CUDA, numpy and Python RNG states as tensors and plain values (loadable with weights_only)."""
    np_name, np_keys, np_pos, np_has_gauss, np_gauss = np.random.get_state()
    py_version, py_state, py_gauss = random.getstate()
    state = {
        "torch": torch.get_rng_state(),
        "numpy": {
            "name": np_name,
            "keys": torch.from_numpy(np_keys.astype(np.int64)),
            "pos": int(np_pos),
            "has_gauss": int(np_has_gauss),
            "cached_gaussian": float(np_gauss),
        },
        "python": {
            "version": int(py_version),
            "state": torch.tensor(py_state, dtype=torch.int64),
            "gauss_next": py_gauss,
        },
    }
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict) -> None:
    """Restore the states :func:`rng_state` captured."""
    torch.set_rng_state(state["torch"])
    np_state = state["numpy"]
    np.random.set_state(
        (
            np_state["name"],
            np_state["keys"].numpy().astype(np.uint32),
            np_state["pos"],
            np_state["has_gauss"],
            np_state["cached_gaussian"],
        )
    )
    py_state = state["python"]
    random.setstate((py_state["version"], tuple(int(v) for v in py_state["state"].tolist()), py_state["gauss_next"]))
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])
