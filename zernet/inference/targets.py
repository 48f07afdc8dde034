"""How targets and input features are shown to the network: transforms and standardisation.

Regression targets are trained in *trained units*: ``target_transform`` (``none`` or ``log``) first, then
``(y - mean) / std`` with the mean and standard deviation over every training vertex. The statistics are
a plain dictionary ``{"transform", "mean", "std"}`` stored in the checkpoint, so predictions of a trained
model are turned back into the target's own units exactly as in training. Input features may be
standardised per channel the same way (``{"mean": [...], "std": [...]}``).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np
import torch

from zernet.inference.errors import ConfigError

__all__ = [
    "target_stats",
    "feature_stats",
    "mean_std",
    "standardise",
    "unstandardise",
    "destandardise",
    "untransform",
    "standardise_features",
]


def mean_std(arrays: Iterable, flat_std: float) -> tuple[np.ndarray, np.ndarray]:
    """Mean and standard deviation over the rows of all ``arrays`` together (per column for 2-D arrays,
    one pair for 1-D ones), in one pass; a deviation below ``flat_std`` is replaced by 1."""
    total = total_sq = 0.0
    count = 0
    for x in arrays:
        x = np.asarray(x, dtype=np.float64)
        total = total + x.sum(axis=0)
        total_sq = total_sq + (x**2).sum(axis=0)
        count += len(x)
    mean = np.asarray(total / count)
    std = np.sqrt(np.maximum(total_sq / count - mean**2, 0.0))
    return mean, np.where(std < flat_std, 1.0, std)


def target_stats(dataset, indices: Sequence[int], transform: str = "none", standardize: bool = True) -> dict:
    """How regression targets are shown to the network: ``transform`` (none or log), then standardisation
    with the mean and standard deviation of every training vertex's (transformed) target."""
    if not standardize:
        return {"transform": transform, "mean": 0.0, "std": 1.0}

    def trained_units(i):
        target = np.asarray(dataset.target(i), dtype=np.float64).ravel()  # no operator build for cached shapes
        if transform != "log":
            return target
        if not np.all(target > 0):
            bad = int(np.flatnonzero(~(target > 0))[0])
            raise ConfigError(
                f"train.target_transform log needs positive targets, but shape "
                f"{dataset.names[i]} has {float(target[bad])!r} at vertex {bad}"
            )
        return np.log(target)

    mean, std = mean_std((trained_units(i) for i in indices), flat_std=1e-12)
    return {"transform": transform, "mean": float(mean), "std": float(std)}


def feature_stats(dataset, indices: Sequence[int]) -> dict:
    """Per-channel mean and standard deviation of the input features over every training vertex.

    Inputs such as ``features: shape`` mix channels whose spread differs by two orders of magnitude (high
    Zernike orders ~0.005, boundary distance ~1); without this the network sees mostly the largest ones.
    """
    # A constant channel (e.g. "ones") is only centred.
    mean, std = mean_std((dataset[i].features for i in indices), flat_std=1e-8)
    return {"mean": mean.tolist(), "std": std.tolist()}


def standardise_features(features: torch.Tensor, stats: dict) -> torch.Tensor:
    """``(x - mean) / std`` per channel with :func:`feature_stats`."""
    mean = torch.as_tensor(stats["mean"], dtype=features.dtype, device=features.device)
    std = torch.as_tensor(stats["std"], dtype=features.dtype, device=features.device)
    return (features - mean) / std


def standardise(target: torch.Tensor, stats: dict) -> torch.Tensor:
    """Target in the units the network is trained in (see :func:`target_stats`)."""
    target = target.float()
    if stats.get("transform", "none") == "log":
        target = torch.log(target)
    return (target - stats["mean"]) / stats["std"]


def unstandardise(values: torch.Tensor, stats: dict | None) -> torch.Tensor:
    """Inverse of :func:`standardise`: network output back to the target's units."""
    return untransform(destandardise(values, stats), stats)


def destandardise(values: torch.Tensor, stats: dict | None) -> torch.Tensor:
    """Network output -> transformed target units (e.g. log stress): undo the standardisation only."""
    if stats is None:
        return values
    return values * stats["std"] + stats["mean"]


def untransform(values: torch.Tensor, stats: dict | None) -> torch.Tensor:
    """Transformed target units -> the target's units (undo ``target_transform``)."""
    if stats is not None and stats.get("transform", "none") == "log":
        return torch.exp(values)
    return values
