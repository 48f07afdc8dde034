"""Shared by the benchmarks that compare two ways of running the same training steps
(``bench_prefetch``, ``bench_denormals``, ``bench_paper_layer``): time a pass of ``train_one_epoch``, alternate the variants
over rounds (so a slow minute of the machine hits both), print the medians and their ratio.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable, Sequence

import torch

from zernet.distributed import DistributedContext
from zernet.training.epoch import Objective, train_one_epoch

#: The objective of a correspondence run: every vertex a class, no target scaling.
CORRESPONDENCE = Objective("classification", "cross_entropy", None, None)


def seconds_per_step(
    model: torch.nn.Module, optimizer: torch.optim.Optimizer, dataset, shapes: Sequence[int], epoch: int, train
) -> float:
    """Wall seconds per optimiser step of one ``train_one_epoch`` pass over ``shapes`` (one process)."""
    started = time.perf_counter()
    train_one_epoch(
        model, model, optimizer, dataset, shapes, epoch, train, CORRESPONDENCE, DistributedContext(), progress=False
    )
    return (time.perf_counter() - started) / len(shapes)


def alternate(variants: dict[str, Callable[[], float]], rounds: int) -> dict[str, list[float]]:
    """Each variant once per round, in the given order, for ``rounds`` rounds: ``{name: [seconds, ...]}``."""
    times: dict[str, list[float]] = {name: [] for name in variants}
    for _ in range(rounds):
        for name, run in variants.items():
            times[name].append(run())
    return times


def print_medians(heading: str, label: str, times: dict[str, list[float]], faster: str) -> tuple[dict, float]:
    """Print the median seconds per step of every variant under ``heading`` (``label`` names the first
    column) and how many times as fast ``faster`` is as the first variant; returns the medians and that
    ratio."""
    medians = {name: statistics.median(values) for name, values in times.items()}
    width = max(len(label), *(len(name) for name in medians))
    print(heading)
    print(f"{label:{width}} {'s / step':>9}")
    for name, value in medians.items():
        print(f"{name:{width}} {value:9.2f}")
    first = next(iter(medians))
    ratio = medians[first] / medians[faster]
    print(f"steps {faster}: {ratio:.2f}x as fast as {first}")
    return medians, ratio
