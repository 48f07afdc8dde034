"""Distributed data-parallel training on PyTorch's own engine (``torch.distributed``, started with ``torchrun``).

``zernet train`` needs no special flag: started under ``torchrun`` (which sets ``RANK``, ``WORLD_SIZE``,
``LOCAL_RANK``, ``MASTER_ADDR`` and ``MASTER_PORT``), :func:`setup` joins the process group and training
wraps the model in :class:`~torch.nn.parallel.DistributedDataParallel`::

    torchrun --standalone --nproc_per_node 2 -m zernet.cli train configs/demo.yaml --run-dir runs/ddp

What each rank does:

- **Backend** from the training device: NCCL when the model runs on CUDA (rank ``r`` takes GPU
  ``LOCAL_RANK``), gloo on the CPU. ``ZERNET_DIST_BACKEND`` overrides the choice.
- **Shapes**: every rank computes the same seeded permutation of the training shapes for the epoch
  (:func:`zernet.training.schedule.epoch_order`) and takes the slice ``order[rank::world_size]`` (:func:`shard_indices`).
  The per-rank counts must be equal, or the ranks would run different numbers of optimiser steps and the
  gradient all-reduce would deadlock; so the permutation is **padded by repeating its first shapes** up to a
  multiple of ``world_size`` (every shape is seen at least once per epoch; at most ``world_size - 1`` shapes
  twice). ``remainder="drop"`` instead leaves the last ``len % world_size`` shapes of the permutation out (a
  different set each epoch).
- **Gradients**: DDP averages them over the ranks, so one step equals a single-process step whose loss is
  the mean of the ranks' losses (each rank's loss is the vertex mean over its ``shapes_per_step`` shapes).
  The effective batch is ``world_size × shapes_per_step`` shapes, so the learning rate may need raising.
- **Randomness**: the model starts identical everywhere (same seed; DDP also broadcasts rank 0's weights).
  Dropout then draws from a generator reseeded at every epoch from ``(seed, epoch, rank)``
  (:meth:`DistributedContext.seed_epoch`): the ranks draw different masks, and a resumed distributed run
  repeats the uninterrupted one exactly without per-rank RNG states in the checkpoint.
- **Files**: only rank 0 (:func:`is_main`) writes checkpoints, ``train.log``, ``config.yaml`` and
  ``metrics.json``, and evaluates on the test split at the end. Rank 0 preprocesses the shapes first
  (:meth:`DistributedContext.main_first`); the other ranks then read them from the cache. On ``--resume``
  every rank loads the same checkpoint, so the run folder and ``cache_dir`` must be on a file system all
  ranks see (automatic on one machine).
- **Validation**: the validation shapes are split across the ranks (no padding) and the per-shape means
  combined exactly (:meth:`DistributedContext.mean_over_shards`), so every rank takes the same early-stopping
  decision.

Collectives wait at most ``ZERNET_DIST_TIMEOUT_MINUTES`` (default 120) — long, because the other ranks wait
at a barrier while rank 0 preprocesses the data set.
"""

from __future__ import annotations

import contextlib
import datetime
import gc
import os
import random
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel

__all__ = [
    "DistributedContext",
    "setup",
    "get_rank",
    "get_world_size",
    "is_main",
    "barrier",
    "launched_with_torchrun",
    "backend_for",
    "shard_indices",
    "ENV_TIMEOUT",
    "ENV_BACKEND",
]

#: Minutes a collective (e.g. the barrier while rank 0 preprocesses) may wait before failing.
ENV_TIMEOUT = "ZERNET_DIST_TIMEOUT_MINUTES"
#: Force a backend (``gloo``, ``nccl``) instead of choosing it from the device.
ENV_BACKEND = "ZERNET_DIST_BACKEND"
_DEFAULT_TIMEOUT_MINUTES = 120.0


def _env_int(name: str, default: int) -> int:
    value = os.environ.get(name)
    if value is None or value == "":
        return default
    try:
        return int(value)
    except ValueError:
        raise RuntimeError(f"environment variable {name}={value!r} is not an integer") from None


def launched_with_torchrun() -> bool:
    """True when this process is one of several started by ``torchrun`` (``WORLD_SIZE`` > 1)."""
    return _env_int("WORLD_SIZE", 1) > 1


def get_rank() -> int:
    """This process's rank: from the process group when it exists, else from ``RANK`` (0 when not set).

    Reading the environment lets code that runs before the group is joined (e.g. deleting stale files of a
    fresh run) already act on rank 0 only.
    """
    if dist.is_available() and dist.is_initialized():
        return dist.get_rank()
    return _env_int("RANK", 0)


def get_world_size() -> int:
    """Number of processes: from the process group when it exists, else ``WORLD_SIZE`` (1 when not set)."""
    if dist.is_available() and dist.is_initialized():
        return dist.get_world_size()
    return _env_int("WORLD_SIZE", 1)


def is_main() -> bool:
    """True on rank 0 — the only rank that writes checkpoints, logs and metrics."""
    return get_rank() == 0


def barrier() -> None:
    """Wait for every rank (a no-op without a process group)."""
    if dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1:
        dist.barrier()


def backend_for(device: torch.device) -> str:
    """``nccl`` for CUDA devices, ``gloo`` otherwise (``ZERNET_DIST_BACKEND`` overrides)."""
    forced = os.environ.get(ENV_BACKEND)
    if forced:
        return forced
    return "nccl" if torch.device(device).type == "cuda" else "gloo"


def shard_indices(order: Sequence[int], rank: int, world_size: int, remainder: str = "pad") -> list[int]:
    """This rank's share of an epoch's shape order, the same length on every rank.

    Args:
        order: the epoch's permutation of shape indices (identical on every rank).
        rank, world_size: this process and the number of processes.
        remainder: ``"pad"`` repeats the order cyclically from its start up to a multiple of ``world_size``
            (every shape is used; works even with fewer shapes than ranks); ``"drop"`` cuts the order down
            to a multiple of ``world_size`` (no shape twice; needs at least ``world_size`` shapes).

    Returns:
        ``order'[rank::world_size]`` where ``order'`` is the padded or cut order.
    """
    if world_size < 1 or not 0 <= rank < world_size:
        raise ValueError(f"rank {rank} is not in 0..{world_size - 1}")
    order = list(order)
    n = len(order)
    if n == 0:
        raise ValueError("no shapes to share among the ranks")
    if remainder == "pad":
        total = -(-n // world_size) * world_size
        order = [order[i % n] for i in range(total)]
    elif remainder == "drop":
        total = (n // world_size) * world_size
        if total == 0:
            raise ValueError(f"{n} shape(s) cannot be shared among {world_size} ranks with remainder='drop'")
        order = order[:total]
    else:
        raise ValueError(f"remainder must be 'pad' or 'drop', got {remainder!r}")
    return order[rank::world_size]


@dataclass
class DistributedContext:
    """Where this process stands in a (possibly single-process) training job.

    With ``world_size == 1`` every method is a cheap no-op or the identity, so the training loop runs the
    same code with and without ``torchrun``.
    """

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))
    backend: str | None = None
    owns_group: bool = False  # True when setup() created the group, so close() destroys it

    @property
    def distributed(self) -> bool:
        return self.world_size > 1

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    def barrier(self) -> None:
        if self.distributed:
            dist.barrier()

    def shard(self, order: Sequence[int], remainder: str = "pad") -> list[int]:
        """This rank's equal share of ``order`` (see :func:`shard_indices`); ``order`` itself on one process."""
        if not self.distributed:
            return list(order)
        return shard_indices(order, self.rank, self.world_size, remainder)

    def wrap(self, model: torch.nn.Module) -> torch.nn.Module:
        """``DistributedDataParallel(model)`` in a distributed run, the model itself otherwise.

        ``device_ids`` stays None even on a GPU: the model is already on its device and the inputs are moved
        by the caller; with device_ids DDP would try to move a :class:`~zernet.operators.batch.Geometry`
        argument (sparse operators inside) itself.
        """
        if not self.distributed:
            return model
        return DistributedDataParallel(model, device_ids=None)

    @staticmethod
    def unwrap(model: torch.nn.Module) -> torch.nn.Module:
        """The plain model inside a DDP wrapper (its state dict has no ``module.`` prefix)."""
        return getattr(model, "module", model)

    def seed_epoch(self, seed: int, epoch: int) -> None:
        """Distributed runs only: reseed torch, numpy and Python RNGs from ``(seed, epoch, rank)``.

        Gives each rank its own dropout masks and makes the RNG at the start of an epoch independent of
        history, which a resumed run needs (the checkpoint holds rank 0's RNG state only).
        """
        if not self.distributed:
            return
        mixed = ((int(seed) * 1_000_003 + int(epoch)) * 65_537 + self.rank) % (2**63 - 1)
        torch.manual_seed(mixed)  # also seeds every CUDA device
        np.random.seed(mixed % 2**32)
        random.seed(mixed)

    def sum_over_ranks(self, *values: float) -> tuple[float, ...]:
        """Element-wise sums of ``values`` over the ranks (float64; the values themselves on one process)."""
        if not self.distributed:
            return tuple(float(v) for v in values)
        tensor = torch.tensor([float(v) for v in values], dtype=torch.float64, device=self.device)
        dist.all_reduce(tensor, op=dist.ReduceOp.SUM)
        return tuple(tensor.cpu().tolist())

    def mean_over_shards(self, compute: Callable[[list[int]], dict], indices: Sequence[int]) -> dict:
        """``compute(indices)`` — a dict of per-item means — evaluated in parts across the ranks.

        Rank r evaluates ``indices[r::world_size]`` (no padding, so every item counts exactly once); the
        parts' means are recombined weighted by their sizes, identically on every rank. A rank whose part is
        empty contributes nothing.
        """
        indices = list(indices)
        if not self.distributed:
            return compute(indices)
        part = indices[self.rank :: self.world_size]
        local = (len(part), compute(part) if part else {})
        gathered: list = [None] * self.world_size
        dist.all_gather_object(gathered, local)
        total = sum(count for count, _ in gathered)
        keys = next(result for count, result in gathered if count).keys()
        return {key: float(sum(count * result[key] for count, result in gathered if count) / total) for key in keys}

    @contextlib.contextmanager
    def main_first(self) -> Iterator[None]:
        """Run the block on rank 0 first, then on the other ranks (e.g. preprocessing into a shared cache)."""
        if not self.distributed:
            yield
            return
        if not self.is_main:
            dist.barrier()
        yield
        if self.is_main:
            dist.barrier()

    def close(self, completed: bool = True) -> None:
        """Leave the process group if :func:`setup` created it.

        After a completed run every rank first meets at a barrier, so none leaves while another still has a
        collective in flight, and the objects that hold Gloo's pending work (DDP's reducer) are collected
        while the interpreter is whole: freed during interpreter shutdown instead, a rank was once
        aborted at exit ("terminate called without an active exception") after the run had finished. A
        failed run skips the barrier (the other ranks may never reach it).
        """
        if self.owns_group and dist.is_initialized():
            if completed:
                dist.barrier()
            gc.collect()
            dist.destroy_process_group()
            self.owns_group = False


def setup(device: torch.device | str = "cpu") -> DistributedContext:
    """Join the ``torchrun`` process group if there is one; return this process's :class:`DistributedContext`.

    - An existing process group (created by the caller) is used as it is and left open by ``close()``.
    - Otherwise, with ``WORLD_SIZE`` > 1 the group is created from the torchrun environment variables with
      :func:`backend_for` ``(device)``. A CUDA device becomes ``cuda:LOCAL_RANK`` (modulo the visible GPUs):
      each rank needs its own GPU, so an index given in the configuration is ignored here.
    - Without either, a single-process context is returned.
    """
    device = torch.device(device)
    initialized = dist.is_available() and dist.is_initialized()
    if not initialized and not launched_with_torchrun():
        return DistributedContext(device=device)
    if not dist.is_available():
        raise RuntimeError("WORLD_SIZE > 1 but this torch build has no torch.distributed support")

    local_rank = _env_int("LOCAL_RANK", _env_int("RANK", 0))
    if device.type == "cuda":
        device = torch.device("cuda", local_rank % max(torch.cuda.device_count(), 1))
        torch.cuda.set_device(device)
    if initialized:
        return DistributedContext(
            dist.get_rank(), dist.get_world_size(), local_rank, device, dist.get_backend(), owns_group=False
        )

    missing = [name for name in ("RANK", "MASTER_ADDR", "MASTER_PORT") if not os.environ.get(name)]
    if missing:
        raise RuntimeError(
            f"WORLD_SIZE={os.environ['WORLD_SIZE']} but {', '.join(missing)} not set: start "
            "distributed training with torchrun (e.g. torchrun --standalone --nproc_per_node 2 "
            "-m zernet.cli train CONFIG)"
        )
    backend = backend_for(device)
    minutes = float(os.environ.get(ENV_TIMEOUT) or _DEFAULT_TIMEOUT_MINUTES)
    dist.init_process_group(backend, init_method="env://", timeout=datetime.timedelta(minutes=minutes))
    return DistributedContext(dist.get_rank(), dist.get_world_size(), local_rank, device, backend, owns_group=True)
