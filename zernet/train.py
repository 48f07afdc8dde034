"""Training, evaluation and prediction: one loop for every model, data set and task.

The public entry points are:

- :func:`train` ``(config, run_dir, resume=False, progress=True) -> metrics`` — trains a model described by a
  configuration dictionary (normally read from a YAML file, see ``configs/``), selects the best epoch on a
  validation split carved from the training shapes, evaluates that model on the test split and writes a
  complete run folder:

  ``config.yaml``  the full configuration with defaults filled in;
  ``last.pt``      checkpoint after the latest epoch (model, optimiser, RNG states, history, config);
  ``previous.pt``  the ``last.pt`` of the epoch before: ``resume`` falls back to it if last.pt is damaged;
  ``best.pt``      checkpoint of the epoch with the best validation metric;
  ``train.log``    what happened, one line per event and per epoch;
  ``metrics.json`` the validation-selected model evaluated on the test shapes;
  ``plots/``       training curves, the geodesic error curve (correspondence), renders of test shapes.

- :func:`evaluate` ``(run_dir or checkpoint, dataset=None, split="test") -> metrics``.
- :func:`predict` ``(checkpoint, surface) -> per-vertex predictions``.

Reproducibility and resuming. Every random choice is seeded from the configuration: the model's
initialisation and dropout use torch's global generator (seeded once), and the order in which the
training shapes are visited in epoch ``e`` is a permutation drawn from a *fresh* generator seeded with
``(train.seed, e)`` (:func:`epoch_order`), so it depends on nothing but the seed and the epoch — a resumed
run or any rank of a distributed run computes the same order without shared state. The checkpoint written
after every epoch holds the torch, numpy and Python RNG states, the optimiser state and the early-stopping
counters, so ``resume=True`` continues exactly where the last checkpoint left off: the final weights equal
those of an uninterrupted run.

Checkpoints contain only tensors and plain containers (dicts, lists, strings, numbers), so they load with
``torch.load(weights_only=True)``: a crafted checkpoint cannot run code.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import logging
import math
import random
import re
import time
import zipfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
import yaml

from zernet.distributed import DistributedContext, is_main, setup as setup_distributed
from zernet.io_utils import atomic_save_torch, atomic_write_bytes, snapshot_file

__all__ = [
    "ConfigError",
    "DEFAULT_CONFIG",
    "load_config",
    "apply_overrides",
    "resolve_config",
    "build_dataset",
    "train",
    "evaluate",
    "predict",
    "load_checkpoint",
    "epoch_order",
    "precision_autocast",
]

CHECKPOINT_FORMAT = "zernet-checkpoint-1"

# Every key the loop itself understands, with its default. ``data`` and ``model`` additionally pass any
# other key through to the data-set loader and to ``build_model``, which reject what they do not know.
DEFAULT_CONFIG: dict[str, Any] = {
    "data": {
        "kind": "synthetic",      # synthetic | faust | segmentation | regression | aneurysm
        "seed": 0,                # seeds the validation split carved from the training shapes
        "val_fraction": None,     # share of the training shapes held out for model selection
        "val_count": None,        # or an exact number (overrides val_fraction); neither: the loader's default
    },
    "patch": {
        "area": None,             # every surface is scaled to this total area first (None: the data set's default)
        "scales": [],             # one PatchConfig dict per scale, e.g. {r0: 5.5}; []: the data set's default
    },
    "model": {
        "name": "zernet",
    },
    "train": {
        "epochs": 200,
        "lr": 1.0e-3,
        "lr_schedule": "constant",    # constant | cosine (from lr down to 0 over train.epochs, per epoch)
        "weight_decay": 0.0,
        "loss": "auto",               # auto (cross_entropy / mse by task) | cross_entropy | mse | l1 | relative_l1
        "standardize_targets": True,  # regression: train on (y - mean) / std of the training targets
        "target_transform": "none",   # regression: none | log (train on log y: the loss sees relative errors)
        "standardize_features": False,  # feed (x - mean) / std per input channel, from the training vertices
        "patience": 20,               # stop after this many epochs without a better validation metric
        "seed": 0,
        "shapes_per_step": 1,         # surfaces concatenated into one optimiser step
        "device": "auto",             # auto (cuda if available, else cpu) | cpu | cuda | cuda:1 ...
        "threads": None,              # torch CPU threads (None: torch's default)
        "grad_clip": None,            # clip the gradient norm to this value (None: no clipping)
        "precision": "float32",       # float32 | bfloat16: linear layers under torch.autocast in bfloat16
                                      # (convolutions stay float32); ~3x faster matmuls on CPUs with
                                      # AVX-512 BF16 or AMX and on recent GPUs, slower on CPUs without them
    },
    "eval": {
        "renders": 3,                 # test shapes rendered as pictures (prediction, truth, error)
        "plots": True,                # write plots at all (training curves, error curve, renders)
    },
    "cache_dir": ".zernet-cache",     # preprocessed patch operators, reused across runs
}

_PASS_THROUGH_SECTIONS = ("data", "model")
_LOSSES = ("auto", "cross_entropy", "mse", "l1", "relative_l1")
_TARGET_TRANSFORMS = ("none", "log")
_LR_SCHEDULES = ("constant", "cosine")
_PRECISIONS = ("float32", "bfloat16")


class ConfigError(ValueError):
    """A configuration that cannot be used; the message names the offending key."""


# --------------------------------------------------------------------------------------------------------
# Configuration
# --------------------------------------------------------------------------------------------------------


class _ConfigLoader(yaml.SafeLoader):
    """YAML 1.1 reads ``1e-3`` as a string (it wants ``1.0e-3``); configs mean a number, so read it as one."""


_ConfigLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"),
)


def _parse_yaml(text: str):
    return yaml.load(text, Loader=_ConfigLoader)


def load_config(path: str | Path) -> dict:
    """Read a YAML configuration file into a plain dictionary (defaults are filled in by :func:`resolve_config`)."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"config file not found: {path}")
    try:
        config = _parse_yaml(path.read_text(encoding="utf-8"))
    except yaml.YAMLError as error:
        raise ConfigError(f"{path}: not valid YAML ({error})") from None
    if config is None:
        config = {}
    if not isinstance(config, dict):
        raise ConfigError(f"{path}: the top level must be a mapping of sections, got {type(config).__name__}")
    return config


def apply_overrides(config: dict, overrides: Sequence[str]) -> dict:
    """Return a copy of ``config`` with dotted ``key=value`` overrides applied.

    Values are parsed as YAML, so ``train.epochs=5`` gives an int, ``model.widths=[32,64]`` a list and
    ``data.root=~/faust`` a string. ``patch.scales.0.r0=4.5`` indexes into a list.
    """
    config = copy.deepcopy(config)
    for override in overrides:
        key, sep, raw = override.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"override {override!r} is not of the form section.key=value")
        try:
            value = _parse_yaml(raw)
        except yaml.YAMLError:
            value = raw
        parts = key.strip().split(".")
        node: Any = config
        for depth, part in enumerate(parts[:-1]):
            where = ".".join(parts[: depth + 1])
            if isinstance(node, list):
                node = node[_list_index(part, node, where)]
            else:
                if part not in node or node[part] is None:
                    node[part] = {}
                node = node[part]
            if not isinstance(node, (dict, list)):
                raise ConfigError(f"override {override!r}: {where} is a value, not a section")
        last = parts[-1]
        if isinstance(node, list):
            node[_list_index(last, node, key)] = value
        else:
            node[last] = value
    return config


def _list_index(part: str, node: list, where: str) -> int:
    try:
        index = int(part)
    except ValueError:
        raise ConfigError(f"override key {where}: expected a list index, got {part!r}") from None
    if not -len(node) <= index < len(node):
        raise ConfigError(f"override key {where}: index {index} out of range (list of {len(node)})")
    return index


def resolve_config(config: dict) -> dict:
    """Fill in defaults and check every key and value the training loop relies on.

    Unknown top-level sections and unknown keys in ``train``, ``patch`` (and each scale) and ``eval`` are
    errors that name the key — a typo must not silently fall back to a default. Keys in ``data`` and
    ``model`` other than the generic ones go to the loader and to ``build_model``, which check them.
    """
    from zernet.patches import PatchConfig

    if not isinstance(config, dict):
        raise ConfigError(f"config must be a mapping of sections, got {type(config).__name__}")
    unknown = set(config) - set(DEFAULT_CONFIG)
    if unknown:
        raise ConfigError(
            f"unknown config section {sorted(unknown)[0]!r} (known: {', '.join(sorted(DEFAULT_CONFIG))})"
        )
    resolved: dict[str, Any] = {}
    for section, defaults in DEFAULT_CONFIG.items():
        given = config.get(section)
        if not isinstance(defaults, dict):
            resolved[section] = defaults if given is None else given
            continue
        if given is None:
            given = {}
        if not isinstance(given, dict):
            raise ConfigError(f"config section {section!r} must be a mapping, got {type(given).__name__}")
        if section not in _PASS_THROUGH_SECTIONS:
            extra = set(given) - set(defaults)
            if extra:
                raise ConfigError(
                    f"unknown key {section}.{sorted(extra)[0]} (known: {', '.join(sorted(defaults))})"
                )
        merged = copy.deepcopy(defaults)
        merged.update(copy.deepcopy(given))
        resolved[section] = merged

    train_cfg = resolved["train"]
    _check_int(train_cfg, "train.epochs", minimum=0)
    _check_int(train_cfg, "train.patience", minimum=1, allow_none=True)
    _check_int(train_cfg, "train.seed", minimum=0)
    _check_int(train_cfg, "train.shapes_per_step", minimum=1)
    _check_int(train_cfg, "train.threads", minimum=1, allow_none=True)
    _check_number(train_cfg, "train.lr", positive=True)
    _check_number(train_cfg, "train.weight_decay")
    _check_number(train_cfg, "train.grad_clip", positive=True, allow_none=True)
    if train_cfg["loss"] not in _LOSSES:
        raise ConfigError(f"train.loss must be one of {', '.join(_LOSSES)}, got {train_cfg['loss']!r}")
    if train_cfg["lr_schedule"] not in _LR_SCHEDULES:
        raise ConfigError(f"train.lr_schedule must be one of {', '.join(_LR_SCHEDULES)}, "
                          f"got {train_cfg['lr_schedule']!r}")
    if train_cfg["target_transform"] not in _TARGET_TRANSFORMS:
        raise ConfigError(f"train.target_transform must be one of {', '.join(_TARGET_TRANSFORMS)}, "
                          f"got {train_cfg['target_transform']!r}")
    if train_cfg["precision"] not in _PRECISIONS:
        raise ConfigError(f"train.precision must be one of {', '.join(_PRECISIONS)}, got {train_cfg['precision']!r}")
    if not isinstance(train_cfg["device"], str):
        raise ConfigError(f"train.device must be a string such as auto, cpu or cuda, got {train_cfg['device']!r}")

    data_cfg = resolved["data"]
    if not isinstance(data_cfg.get("kind"), str):
        raise ConfigError("data.kind must name a data set kind (synthetic, faust, segmentation, regression, aneurysm)")
    _check_int(data_cfg, "data.seed", minimum=0)
    _check_int(data_cfg, "data.val_count", minimum=0, allow_none=True)
    _check_number(data_cfg, "data.val_fraction", allow_none=True)
    if data_cfg["val_fraction"] is not None and not 0.0 <= float(data_cfg["val_fraction"]) < 1.0:
        raise ConfigError(f"data.val_fraction must be in [0, 1), got {data_cfg['val_fraction']}")

    model_cfg = resolved["model"]
    from zernet.nn.models import available_models

    models = available_models()
    if model_cfg.get("name") not in models:
        # Checked here, before any preprocessing, so a typo fails in a second rather than after minutes.
        raise ConfigError(f"model.name {model_cfg.get('name')!r} is not a model (known: {', '.join(models)})")

    patch_cfg = resolved["patch"]
    _check_number(patch_cfg, "patch.area", positive=True, allow_none=True)
    scales = patch_cfg["scales"]
    if not isinstance(scales, list):
        raise ConfigError("patch.scales must be a list of patch settings, one per scale (e.g. [{r0: 5.5}]), "
                          "or [] for the data set's default")
    known = {f.name for f in dataclasses.fields(PatchConfig)}
    for i, scale in enumerate(scales):
        if not isinstance(scale, dict):
            raise ConfigError(f"patch.scales.{i} must be a mapping of PatchConfig fields, got {scale!r}")
        extra = set(scale) - known
        if extra:
            raise ConfigError(f"unknown key patch.scales.{i}.{sorted(extra)[0]} (known: {', '.join(sorted(known))})")
        if "r0" not in scale:
            raise ConfigError(f"patch.scales.{i}.r0 (the patch radius) is required")
        try:
            PatchConfig(**scale)
        except (TypeError, ValueError) as error:
            raise ConfigError(f"patch.scales.{i}: {error}") from None

    eval_cfg = resolved["eval"]
    _check_int(eval_cfg, "eval.renders", minimum=0)
    if resolved["cache_dir"] is not None and not isinstance(resolved["cache_dir"], str):
        raise ConfigError(f"cache_dir must be a folder path or null, got {resolved['cache_dir']!r}")
    return resolved


def _check_int(section: dict, dotted: str, minimum: int | None = None, allow_none: bool = False) -> None:
    key = dotted.rsplit(".", 1)[1]
    value = section.get(key)
    if value is None and allow_none:
        return
    if isinstance(value, bool) or not isinstance(value, int):
        raise ConfigError(f"{dotted} must be an integer, got {value!r}")
    if minimum is not None and value < minimum:
        raise ConfigError(f"{dotted} must be >= {minimum}, got {value}")


def _check_number(section: dict, dotted: str, positive: bool = False, allow_none: bool = False) -> None:
    key = dotted.rsplit(".", 1)[1]
    value = section.get(key)
    if value is None and allow_none:
        return
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ConfigError(f"{dotted} must be a number, got {value!r}")
    if positive and value <= 0:
        raise ConfigError(f"{dotted} must be > 0, got {value}")


def patch_configs(config: dict) -> list:
    """The list of :class:`~zernet.patches.PatchConfig`, one per scale, of a resolved configuration."""
    from zernet.patches import PatchConfig

    return [PatchConfig(**scale) for scale in config["patch"]["scales"]]


def resolve_device(name: str) -> torch.device:
    """``auto`` picks CUDA when available; anything else is handed to ``torch.device`` and checked."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError:
        raise ConfigError(f"train.device: {name!r} is not a device (use auto, cpu, cuda or cuda:N)") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"train.device is {name!r} but CUDA is not available on this machine")
    return device


def precision_autocast(precision: str, device_type: str):
    """The ``torch.autocast`` context of ``train.precision`` for a forward pass on ``device_type``.

    ``"bfloat16"``: linear layers run in bfloat16 (convolutions stay float32, see
    :func:`zernet.nn.conv.float32_forward`); ``"float32"``: a disabled context. Compute the loss on
    ``output.float()`` outside it.
    """
    return torch.autocast(device_type, dtype=torch.bfloat16, enabled=precision == "bfloat16")


def keep_freed_memory() -> bool:
    """Make glibc keep freed CPU memory for reuse instead of handing it back to the kernel.

    A training step on a FAUST-sized mesh allocates and frees tensors of hundreds of MB (the 6,890 x 6,890
    logits and their gradient). glibc serves such blocks with ``mmap`` and returns them with ``munmap``, so
    every step page-faults the same memory in again: about a quarter of a correspondence step on this
    2-core machine (benchmarks/bench_layers.py). Disabling ``mmap`` for large blocks and the heap trim keeps
    the peak footprint unchanged and the pages resident. Called by the ``zernet`` command and the
    benchmarks; a library user may call it too. Returns False where it does not apply (not glibc) and
    leaves the allocator alone when the user set ``MALLOC_MMAP_MAX_`` or ``MALLOC_TRIM_THRESHOLD_``.
    """
    import ctypes
    import os

    if any(name in os.environ for name in ("MALLOC_MMAP_MAX_", "MALLOC_TRIM_THRESHOLD_")):
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    m_trim_threshold, m_mmap_max = -1, -4  # from glibc's malloc.h
    return bool(mallopt(m_mmap_max, 0)) and bool(mallopt(m_trim_threshold, 2**30))


# --------------------------------------------------------------------------------------------------------
# Data and model
# --------------------------------------------------------------------------------------------------------


def build_dataset(config: dict, progress: bool = True, workers: int | None = None):
    """The :class:`~zernet.data.ShapeDataset` a resolved configuration describes (preprocessed and cached).

    Hands ``data.kind`` to :func:`zernet.data.load_dataset` with ``patch.scales``, ``patch.area``,
    ``cache_dir``, ``data.seed``, ``data.val_fraction``/``data.val_count`` and ``data.features`` (as
    ``feature_kind``); every other ``data`` key is a loader option passed by name (``root``, ``test``, ...).
    """
    from zernet.data import DATASET_KINDS, load_dataset

    options = dict(config["data"])
    kind = options.pop("kind")
    if kind not in DATASET_KINDS:
        raise ConfigError(f"data.kind {kind!r} is not a data set kind (known: {', '.join(DATASET_KINDS)})")
    for key in ("val_fraction", "val_count"):
        if options.get(key) is None:
            options.pop(key, None)  # let the loader's default apply
    if "features" in options:
        options["feature_kind"] = options.pop("features")
    try:
        return load_dataset(kind, patch_configs=patch_configs(config), area=config["patch"]["area"],
                            cache_dir=config["cache_dir"], progress=progress, workers=workers, **options)
    except TypeError as error:
        # An option the loader does not take: a configuration problem under data.
        raise ConfigError(f"data (kind {kind}): {error}") from None


def _is_correspondence(dataset, config: dict) -> bool:
    """Correspondence = classification whose class is the vertex index of a shared template."""
    flag = getattr(dataset, "correspondence", None)
    if flag is not None:
        return bool(flag)
    return config["data"]["kind"] == "faust"


def _build_model(spec: dict) -> torch.nn.Module:
    from zernet.nn.models import build_model

    try:
        return build_model(spec["name"], spec["in_channels"], spec["out_channels"], **spec["options"])
    except TypeError as error:
        raise ConfigError(f"model {spec['name']!r}: {error}") from None
    except KeyError as error:
        raise ConfigError(f"model.name: {error.args[0] if error.args else error}") from None


def _model_spec(config: dict, in_channels: int, out_channels: int, patch_configs: Sequence) -> dict:
    """Name, channel counts and options of the model; the Zernike degree follows the patch operators.

    A model's ``n_max`` (or ``k``, the number of bases) must match the operators', so unless the config
    sets it explicitly it is taken from the patch settings — changing ``patch.scales.*.n_max`` alone then
    just works instead of failing with a shape mismatch.
    """
    import inspect

    from zernet.nn.models import MODEL_REGISTRY, available_models
    from zernet.zernike import num_bases

    name = config["model"]["name"]
    options = {k: v for k, v in config["model"].items() if k != "name"}
    degrees = {int(c.n_max) for c in patch_configs}
    if len(degrees) == 1 and "n_max" not in options and "k" not in options:
        available_models()  # registers the plug-in models
        try:
            accepted = inspect.signature(MODEL_REGISTRY[name]).parameters
        except (KeyError, TypeError, ValueError):
            accepted = {}
        n_max = degrees.pop()
        if "n_max" in accepted:
            options["n_max"] = n_max
        elif "k" in accepted:
            options["k"] = num_bases(n_max)
    return {"name": name, "in_channels": int(in_channels), "out_channels": int(out_channels), "options": options}


class _Batch:
    """One optimiser step's input: features, targets and geometry of one or more concatenated surfaces."""

    def __init__(self, records: Sequence, device: torch.device, target_stats: dict | None,
                 feature_stats: dict | None = None):
        from zernet.nn.geometry import Geometry

        self.names = [r.name for r in records]
        self.sizes = [len(r.features) for r in records]
        self.features = torch.from_numpy(np.concatenate([np.asarray(r.features, np.float32) for r in records]))
        self.features = self.features.to(device)
        if feature_stats is not None:
            mean = torch.as_tensor(feature_stats["mean"], dtype=self.features.dtype, device=device)
            std = torch.as_tensor(feature_stats["std"], dtype=self.features.dtype, device=device)
            self.features = (self.features - mean) / std
        geometries = [r.geometry for r in records]
        geometry = geometries[0] if len(geometries) == 1 else Geometry.concatenate(geometries)
        self.geometry = geometry.to(device)
        self.target = None
        if records[0].target is not None:
            target = np.concatenate([np.asarray(r.target) for r in records])
            self.target = torch.from_numpy(target).to(device)
            if target_stats is not None:  # regression on (log-)standardised targets
                self.target = _standardise(self.target, target_stats)


def _loss_name(config: dict, task: str) -> str:
    loss = config["train"]["loss"]
    if loss == "auto":
        return "cross_entropy" if task == "classification" else "mse"
    if task == "classification" and loss != "cross_entropy":
        raise ConfigError(f"train.loss {loss!r} does not fit a classification task (use cross_entropy)")
    if task == "regression" and loss == "cross_entropy":
        raise ConfigError("train.loss cross_entropy does not fit a regression task (use mse, l1 or relative_l1)")
    return loss


def _loss(name: str, output: torch.Tensor, target: torch.Tensor, target_stats: dict | None = None) -> torch.Tensor:
    """Training loss; ``output`` and ``target`` are in the trained units (see :func:`_standardise`).

    ``relative_l1`` is the mean of ``|ŷ - y| / |y|`` in the target's own units, i.e. the MAPE the regression
    is scored with. Its minimiser is not the median that ``l1`` estimates: where a vertex's value is
    uncertain (e.g. near a cut boundary) it predicts lower, because over-predicting a small value costs
    more relative error than under-predicting it by the same factor.
    """
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
    true = _unstandardise(target, target_stats)
    return ((output - target).abs() * std / true.abs()).mean()


def _feature_stats(dataset, indices: Sequence[int]) -> dict:
    """Per-channel mean and standard deviation of the input features over every training vertex.

    Inputs such as ``features: shape`` mix channels whose spread differs by two orders of magnitude (high
    Zernike orders ~0.005, boundary distance ~1); without this the network sees mostly the largest ones.
    """
    # A constant channel (e.g. "ones") is only centred.
    mean, std = _mean_std((dataset[i].features for i in indices), flat_std=1e-8)
    return {"mean": mean.tolist(), "std": std.tolist()}


def _mean_std(arrays, flat_std: float):
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


def _target_stats(dataset, indices: Sequence[int], transform: str = "none", standardize: bool = True) -> dict:
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
            raise ConfigError(f"train.target_transform log needs positive targets, but shape "
                              f"{dataset.names[i]} has {float(target[bad])!r} at vertex {bad}")
        return np.log(target)

    mean, std = _mean_std((trained_units(i) for i in indices), flat_std=1e-12)
    return {"transform": transform, "mean": float(mean), "std": float(std)}


# --------------------------------------------------------------------------------------------------------
# Shape order, RNG states, checkpoints
# --------------------------------------------------------------------------------------------------------


def epoch_learning_rate(train_config: dict, epoch: int) -> float:
    """Learning rate of (1-based) ``epoch``: ``train.lr``, or with ``lr_schedule: cosine`` the half cosine
    from ``lr`` at epoch 1 towards 0 after the last of ``train.epochs``."""
    lr = float(train_config["lr"])
    if train_config.get("lr_schedule", "constant") == "constant":
        return lr
    return 0.5 * lr * (1.0 + math.cos(math.pi * (epoch - 1) / max(int(train_config["epochs"]), 1)))


def epoch_order(seed: int, epoch: int, n: int) -> list[int]:
    """The order of the ``n`` training shapes in ``epoch`` (1-based): a permutation from a generator seeded
    with ``(seed, epoch)`` only, so every process and every resume computes the same order."""
    generator = torch.Generator().manual_seed(int(seed) * 1_000_003 + int(epoch))
    return torch.randperm(n, generator=generator).tolist()


def step_groups(order: Sequence[int], shapes_per_step: int) -> list[list[int]]:
    """Cut an epoch's order into optimiser steps of ``shapes_per_step`` shapes (the last one may be short)."""
    return [list(order[i:i + shapes_per_step]) for i in range(0, len(order), shapes_per_step)]


def _seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def _rng_state() -> dict:
    """torch, CUDA, numpy and Python RNG states as tensors and plain values (loadable with weights_only)."""
    np_name, np_keys, np_pos, np_has_gauss, np_gauss = np.random.get_state()
    py_version, py_state, py_gauss = random.getstate()
    state = {
        "torch": torch.get_rng_state(),
        "numpy": {"name": np_name, "keys": torch.from_numpy(np_keys.astype(np.int64)), "pos": int(np_pos),
                  "has_gauss": int(np_has_gauss), "cached_gaussian": float(np_gauss)},
        "python": {"version": int(py_version), "state": torch.tensor(py_state, dtype=torch.int64),
                   "gauss_next": py_gauss},
    }
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def _set_rng_state(state: dict) -> None:
    torch.set_rng_state(state["torch"])
    np_state = state["numpy"]
    np.random.set_state((np_state["name"], np_state["keys"].numpy().astype(np.uint32), np_state["pos"],
                         np_state["has_gauss"], np_state["cached_gaussian"]))
    py_state = state["python"]
    random.setstate((py_state["version"], tuple(int(v) for v in py_state["state"].tolist()),
                     py_state["gauss_next"]))
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def _cpu_state_dict(module_or_optimizer) -> dict:
    """A state dict with every tensor copied to the CPU, so the checkpoint loads on any machine."""
    def to_cpu(value):
        if isinstance(value, torch.Tensor):
            return value.detach().to("cpu", copy=True)
        if isinstance(value, dict):
            return {k: to_cpu(v) for k, v in value.items()}
        if isinstance(value, list):
            return [to_cpu(v) for v in value]
        if isinstance(value, tuple):
            return tuple(to_cpu(v) for v in value)
        return value

    return to_cpu(module_or_optimizer.state_dict())


def load_checkpoint(path: str | Path) -> dict:
    """Load a zernet checkpoint safely (``weights_only=True``) onto the CPU, with a clear error if unusable."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint not found: {path}")
    # torch.load does not check the zip CRCs, so flipped bytes in the stored tensors would load silently as
    # wrong weights: check them first (torch writes them; it costs one read of the file).
    if zipfile.is_zipfile(path):
        try:
            with zipfile.ZipFile(path) as archive:
                damaged = archive.testzip()
        except Exception as error:
            damaged = f"? ({type(error).__name__}: {error})"
        if damaged is not None:
            raise ValueError(f"{path}: not a readable zernet checkpoint (stored record {damaged} fails its CRC "
                             "check: the file is corrupt)")
    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # truncated, corrupt, or holding objects weights_only refuses
        raise ValueError(f"{path}: not a readable zernet checkpoint ({type(error).__name__}: {error})") from None
    if not isinstance(checkpoint, dict) or checkpoint.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"{path}: not a zernet checkpoint (expected format {CHECKPOINT_FORMAT})")
    return checkpoint


def _checkpoint_path(run_dir_or_checkpoint: str | Path) -> Path:
    """A run folder means its ``best.pt``; a file is taken as it is."""
    path = Path(run_dir_or_checkpoint)
    if path.is_dir():
        best = path / "best.pt"
        if not best.is_file():
            raise FileNotFoundError(f"{path} holds no best.pt: is it a zernet run folder whose training has run?")
        return best
    return path


def _plain(value):
    """Configuration values as plain YAML/JSON types (tuples -> lists, paths -> strings)."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (np.floating,)):
        return float(value)
    return value


# --------------------------------------------------------------------------------------------------------
# Logging
# --------------------------------------------------------------------------------------------------------


class _TqdmHandler(logging.Handler):
    """Console output that does not tear through an active progress bar."""

    def emit(self, record: logging.LogRecord) -> None:
        from tqdm.auto import tqdm

        try:
            tqdm.write(self.format(record))
        except Exception:  # a closed console must not stop training
            self.handleError(record)


def _open_log(run_dir: Path, echo: bool = True, main: bool = True) -> logging.Logger:
    """A logger writing to ``run_dir/train.log`` (appending, so a resumed run keeps its history) and the console.

    ``main=False`` (ranks other than 0 of a distributed run): no file, and only warnings on the console.
    """
    logger = logging.getLogger(f"zernet.run.{run_dir.resolve()}")
    logger.setLevel(logging.INFO)
    logger.propagate = False
    for handler in list(logger.handlers):
        logger.removeHandler(handler)
        handler.close()
    if main:
        file_handler = logging.FileHandler(run_dir / "train.log", mode="a", encoding="utf-8")
        file_handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s", "%Y-%m-%d %H:%M:%S"))
        logger.addHandler(file_handler)
    if echo:
        console = _TqdmHandler()
        console.setFormatter(logging.Formatter("%(message)s"))
        if not main:
            console.setLevel(logging.WARNING)
        logger.addHandler(console)
    return logger


def _close_log(logger: logging.Logger) -> None:
    for handler in list(logger.handlers):
        logger.removeHandler(handler)
        handler.close()


# --------------------------------------------------------------------------------------------------------
# Training
# --------------------------------------------------------------------------------------------------------


def _merge_resume_config(stored: dict, given: dict | None, logger: logging.Logger) -> dict:
    """On resume the stored configuration wins, except that the epoch budget and patience may be raised."""
    config = copy.deepcopy(stored)
    if given is None:
        return config
    given = resolve_config(given)
    for key in ("epochs", "patience"):
        if given["train"][key] != config["train"][key]:
            logger.info(f"resume: train.{key} changed from {config['train'][key]} to {given['train'][key]}")
            config["train"][key] = given["train"][key]
    others = {k: v for k, v in given.items()}
    others["train"] = dict(others["train"], epochs=config["train"]["epochs"], patience=config["train"]["patience"])
    if _plain(others) != _plain(config):
        logger.warning("resume: the given configuration differs from the run's; continuing with the run's own "
                       "config.yaml (only train.epochs and train.patience may change on resume)")
    return config


def train(config: dict | None, run_dir: str | Path, resume: bool = False, progress: bool = True,
          overwrite: bool = False, workers: int | None = None) -> dict:
    """Train, select the best epoch on validation, evaluate it on the test split and fill ``run_dir``.

    Args:
        config: configuration dictionary (see ``DEFAULT_CONFIG`` and ``configs/*.yaml``). With ``resume`` it
            may be ``None`` (the run's own config is used); otherwise only ``train.epochs``/``train.patience``
            may differ from the run's.
        run_dir: the run folder; created if needed.
        resume: continue from ``run_dir/last.pt`` exactly where it stopped.
        progress: show progress bars (preprocessing, steps of each epoch).
        overwrite: start afresh even if ``run_dir`` already holds a checkpoint (otherwise an error, so that a
            finished run is never clobbered by accident).
        workers: processes for preprocessing (None: the data module's default).

    Returns:
        The test metrics (also written to ``run_dir/metrics.json``).
    """
    run_dir = Path(run_dir)
    last_path, best_path = run_dir / "last.pt", run_dir / "best.pt"
    checkpoint, resume_note = None, None
    if resume:
        checkpoint, resume_note = _load_resume_checkpoint(run_dir)
    else:
        if config is None:
            raise ConfigError("train needs a configuration (or resume=True with an existing run folder)")
        config = resolve_config(config)
        if last_path.exists() and not overwrite:
            raise ConfigError(f"{run_dir} already holds a run (last.pt); resume it with --resume or choose "
                              "another --run-dir")
        for stale in (last_path, run_dir / "previous.pt", best_path, run_dir / "metrics.json",
                      run_dir / "train.log"):
            if stale.exists() and is_main():  # in a distributed run only rank 0 touches the run folder
                stale.unlink()
    run_dir.mkdir(parents=True, exist_ok=True)
    logger = _open_log(run_dir, main=is_main())
    ctx = None
    try:
        if resume_note:
            logger.warning(resume_note)
        if checkpoint is not None:
            config = _merge_resume_config(checkpoint["config"], config, logger)
        # Joins the torchrun process group, if any (see zernet.distributed); a no-op for one process.
        ctx = setup_distributed(resolve_device(config["train"]["device"]))
        if ctx.is_main:
            atomic_write_bytes(run_dir / "config.yaml",
                               yaml.safe_dump(_plain(config), sort_keys=False).encode("utf-8"))
        return _train(config, run_dir, checkpoint, progress, logger, workers, ctx)
    finally:
        if ctx is not None:
            ctx.close()
        _close_log(logger)


def _load_resume_checkpoint(run_dir: Path) -> tuple[dict, str | None]:
    """The checkpoint to resume from, and a note when it is not ``last.pt``.

    ``last.pt`` is used when it loads. If it is missing or unusable (truncated, corrupt, crafted), the newest
    usable of ``previous.pt`` (the last.pt of the epoch before) and ``best.pt`` is taken instead: training
    from any checkpoint is deterministic, so the final weights are the same, only an epoch is repeated.
    """
    last = run_dir / "last.pt"
    problems: list[str] = []
    try:
        return load_checkpoint(last), None
    except FileNotFoundError:
        problems.append(f"{last} does not exist")
    except ValueError as error:
        problems.append(str(error))
    candidates = []
    for name in ("previous.pt", "best.pt"):
        try:
            candidates.append((load_checkpoint(run_dir / name), run_dir / name))
        except FileNotFoundError:
            pass
        except ValueError as error:
            problems.append(str(error))
    if not candidates:
        if len(problems) == 1 and not last.exists():
            raise FileNotFoundError(f"cannot resume: {last} does not exist (no epoch has finished yet?)")
        raise ValueError(f"cannot resume {run_dir}: no usable checkpoint: " + "; ".join(problems))
    checkpoint, path = max(candidates, key=lambda item: item[0]["state"]["epoch"])
    note = (f"{problems[0]}; resuming from {path} (after epoch {checkpoint['state']['epoch']}) instead, "
            "repeating the epochs after it")
    return checkpoint, note


def _train(config: dict, run_dir: Path, checkpoint: dict | None, progress: bool, logger: logging.Logger,
           workers: int | None, ctx: DistributedContext) -> dict:
    from tqdm.auto import tqdm

    tcfg = config["train"]
    device = ctx.device  # the configured device; cuda:LOCAL_RANK on each rank of a distributed GPU run
    progress = progress and ctx.is_main
    if tcfg["threads"]:
        torch.set_num_threads(int(tcfg["threads"]))
    logger.info(("resuming" if checkpoint else "starting") + f" run in {run_dir} on {device} "
                f"({torch.get_num_threads()} CPU threads"
                + (f", {ctx.world_size} ranks, {ctx.backend})" if ctx.distributed else ")"))

    started = time.perf_counter()
    with ctx.main_first():  # rank 0 fills the cache; the other ranks then read it
        dataset = build_dataset(config, progress=progress, workers=workers)
    preprocess_seconds = time.perf_counter() - started
    train_idx, val_idx = list(dataset.splits["train"]), list(dataset.splits.get("val", []))
    test_idx = list(dataset.splits.get("test", []))
    if not train_idx:
        raise ConfigError("the data set has no training shapes")
    logger.info(f"data: {config['data']['kind']}, {dataset.task}, {len(train_idx)} train / {len(val_idx)} val / "
                f"{len(test_idx)} test shapes (loaded in {preprocess_seconds:.1f} s)")
    if not val_idx:
        logger.warning("no validation shapes: the last epoch is kept as the model and early stopping is off")

    task = dataset.task
    loss_name = _loss_name(config, task)
    # What predict() needs to preprocess a new surface exactly like the training shapes.
    preprocess_spec = {
        "patch_configs": [_plain(dataclasses.asdict(c)) for c in dataset.patch_configs],
        "area": None if dataset.target_area is None else float(dataset.target_area),
        "feature_kind": str(dataset.feature_kind),
        "class_names": _plain(dataset.info.get("class_names")),
    }
    first = dataset[train_idx[0]]
    out_channels = int(dataset.num_classes) if task == "classification" else 1
    spec = _model_spec(config, first.features.shape[1], out_channels, dataset.patch_configs)

    if checkpoint is not None:
        target_stats = checkpoint["target_stats"]
    elif task == "regression" and (tcfg["standardize_targets"] or tcfg["target_transform"] != "none"):
        target_stats = _target_stats(dataset, train_idx, tcfg["target_transform"], tcfg["standardize_targets"])
        logger.info(f"targets: transform {target_stats['transform']}, standardised with training mean "
                    f"{target_stats['mean']:.6g}, std {target_stats['std']:.6g}")
    else:
        target_stats = None
    if loss_name == "relative_l1":
        for i in train_idx + val_idx:
            target = np.asarray(dataset.target(i)).ravel()
            if not np.all(target != 0):
                bad = int(np.flatnonzero(target == 0)[0])
                raise ConfigError(f"train.loss relative_l1 divides by the target, but shape {dataset.names[i]} "
                                  f"has 0 at vertex {bad}")
    if checkpoint is not None:
        feature_stats = checkpoint.get("feature_stats")
    elif tcfg["standardize_features"]:
        feature_stats = _feature_stats(dataset, train_idx)
        logger.info("input features standardised per channel with the training vertices' mean and std")
    else:
        feature_stats = None

    # Seed right before the model is built, so its initialisation depends only on train.seed.
    _seed_everything(tcfg["seed"])
    model = _build_model(spec).to(device)
    optimizer = torch.optim.Adam(model.parameters(), lr=tcfg["lr"], weight_decay=tcfg["weight_decay"])
    state = {"epoch": 0, "best_metric": None, "best_epoch": 0, "bad_epochs": 0, "stopped": False,
             "stop_reason": "", "train_seconds": 0.0, "history": []}
    if checkpoint is not None:
        model.load_state_dict(checkpoint["model"])
        optimizer.load_state_dict(checkpoint["optimizer"])
        state = checkpoint["state"]
        _set_rng_state(checkpoint["rng"])
        logger.info(f"resumed after epoch {state['epoch']} (best {state['best_metric']} at epoch "
                    f"{state['best_epoch']})")
    # DistributedDataParallel in a distributed run (averages the gradients over the ranks), else the model
    # itself. Only the training forward goes through it; validation, checkpoints and evaluation use `model`.
    net = ctx.wrap(model)
    n_params = sum(p.numel() for p in model.parameters())
    logger.info(f"model {spec['name']} ({n_params:,} parameters), loss {loss_name}, lr {tcfg['lr']} "
                f"({tcfg['lr_schedule']}), "
                f"{tcfg['shapes_per_step']} shape(s) per step")

    higher_is_better = task == "classification"
    monitor = "val_accuracy" if higher_is_better else "val_loss"
    epochs, patience = tcfg["epochs"], tcfg["patience"]
    if state["stopped"] and state["epoch"] < epochs and state["stop_reason"] == "epoch budget":
        state["stopped"] = False  # the budget was raised on resume
    while not state["stopped"] and state["epoch"] < epochs:
        epoch = state["epoch"] + 1
        epoch_started = time.perf_counter()
        net.train()
        ctx.seed_epoch(tcfg["seed"], epoch)  # distributed only: per-rank dropout, exact resume
        for group in optimizer.param_groups:  # a function of the epoch alone: resuming needs no state
            group["lr"] = epoch_learning_rate(tcfg, epoch)
        # One process: the whole permutation. Rank r of W: its equal share order[r::W] (padded, see
        # zernet.distributed.shard_indices), so every rank runs the same number of steps.
        order = ctx.shard([train_idx[i] for i in epoch_order(tcfg["seed"], epoch, len(train_idx))])
        groups = step_groups(order, tcfg["shapes_per_step"])
        loss_sum, hit_sum, vertex_sum = 0.0, 0.0, 0
        bar = tqdm(groups, desc=f"epoch {epoch}/{epochs}", unit="step", leave=False, disable=not progress,
                   dynamic_ncols=True)
        for step, group in enumerate(bar, start=1):
            batch = _Batch([dataset[i] for i in group], device, target_stats, feature_stats)
            optimizer.zero_grad(set_to_none=True)
            with precision_autocast(tcfg["precision"], device.type):
                output = net(batch.features, batch.geometry)
            output = output.float()  # the loss in float32
            loss = _loss(loss_name, output, batch.target, target_stats)
            if not torch.isfinite(loss):
                raise FloatingPointError(
                    f"the training loss became {loss.item()} at epoch {epoch}, step {step} (shapes "
                    f"{', '.join(batch.names)}); lower train.lr or check the targets for NaN/inf"
                )
            loss.backward()
            if tcfg["grad_clip"]:
                torch.nn.utils.clip_grad_norm_(model.parameters(), tcfg["grad_clip"])
            optimizer.step()
            n = int(batch.target.shape[0])
            loss_sum += loss.item() * n
            vertex_sum += n
            postfix = {"loss": f"{loss_sum / vertex_sum:.4g}"}
            if task == "classification":
                hit_sum += (output.detach().argmax(dim=1) == batch.target).sum().item()
                postfix["acc"] = f"{hit_sum / vertex_sum:.3f}"
            bar.set_postfix(postfix)
        bar.close()
        loss_sum, hit_sum, vertex_sum = ctx.sum_over_ranks(loss_sum, hit_sum, vertex_sum)

        entry = {"epoch": epoch, "train_loss": loss_sum / vertex_sum}
        if task == "classification":
            entry["train_accuracy"] = hit_sum / vertex_sum
        if val_idx:
            # Split over the ranks and recombined exactly: every rank sees the same metric and stops alike.
            entry.update(ctx.mean_over_shards(
                lambda part: _validate(model, dataset, part, device, loss_name, target_stats, task,
                                            feature_stats), val_idx))
        entry["seconds"] = time.perf_counter() - epoch_started
        state["train_seconds"] += entry["seconds"]
        state["history"].append(entry)
        state["epoch"] = epoch

        current = entry.get(monitor)
        improved = False
        if current is None:  # no validation: the latest model is the model
            improved = True
        elif state["best_metric"] is None or (current > state["best_metric"] if higher_is_better
                                                else current < state["best_metric"]):
            improved = True
        if improved:
            state["best_metric"] = current
            state["best_epoch"] = epoch
            state["bad_epochs"] = 0
        else:
            state["bad_epochs"] += 1
        if val_idx and patience is not None and state["bad_epochs"] >= patience:
            state["stopped"], state["stop_reason"] = True, f"early stopping (no better {monitor} for {patience} epochs)"
        elif epoch >= epochs:
            state["stopped"], state["stop_reason"] = True, "epoch budget"

        checkpoint = {
            "format": CHECKPOINT_FORMAT,
            "config": _plain(config),
            "model_spec": _plain(spec),
            "task": task,
            "num_classes": None if dataset.num_classes is None else int(dataset.num_classes),
            "correspondence": _is_correspondence(dataset, config),
            "target_stats": target_stats,
            # Area exponent of the regression target: predict() returns values in a new surface's own units.
            "target_exponent": float(dataset.info.get("target_exponent") or 0.0),
            "feature_stats": feature_stats,
            "preprocess": preprocess_spec,
            "model": _cpu_state_dict(model),
            "optimizer": _cpu_state_dict(optimizer),
            "state": copy.deepcopy(state),
            "rng": _rng_state(),
        }
        # best.pt first: if the process dies between the two writes, last.pt still points at the previous
        # epoch, and resuming repeats this epoch identically and rewrites best.pt.
        # previous.pt keeps the last.pt of the epoch before: should last.pt ever be unreadable, resume falls
        # back to it (see _load_resume_checkpoint). Only rank 0 writes in a distributed run.
        if ctx.is_main:
            if improved:
                atomic_save_torch(checkpoint, run_dir / "best.pt")
            snapshot_file(run_dir / "last.pt", run_dir / "previous.pt")
            atomic_save_torch(checkpoint, run_dir / "last.pt")
        logger.info(_epoch_line(entry, epochs, improved))
        if state["stopped"] and state["stop_reason"] != "epoch budget":
            logger.info(f"stopping after epoch {epoch}: {state['stop_reason']}")

    best_text = "n/a" if state["best_metric"] is None else f"{state['best_metric']:.4g}"
    logger.info(f"training done: {state['epoch']} epochs in {state['train_seconds']:.1f} s; best epoch "
                f"{state['best_epoch']} ({monitor} {best_text})")

    if not ctx.is_main:
        # Rank 0 alone evaluates the selected model on the test split and writes metrics.json.
        return {"rank": ctx.rank, "epochs_trained": state["epoch"], "best_epoch": state["best_epoch"],
                "stop_reason": state["stop_reason"]}
    best = load_checkpoint(run_dir / "best.pt")
    model.load_state_dict(best["model"])
    if test_idx:
        split, indices = "test", test_idx
    else:
        logger.warning("the data set has no test shapes: metrics.json reports the validation split instead")
        split, indices = "val", val_idx
    metrics, predictions = _evaluate_model([(model, best)], dataset, indices, device, progress)
    metrics.update({
        "split": split,
        "checkpoint": "best.pt",
        "best_epoch": state["best_epoch"],
        "epochs_trained": state["epoch"],
        "stop_reason": state["stop_reason"],
        "selection": {"metric": monitor, "value": state["best_metric"]},
        "train_seconds": state["train_seconds"],
        "preprocess_seconds": preprocess_seconds,
    })
    if config["eval"]["plots"]:
        try:
            metrics["plots"] = _write_plots(run_dir, state["history"], metrics, predictions, dataset,
                                            config["eval"]["renders"])
        except Exception as error:  # a plotting problem must not throw away a finished training run
            logger.warning(f"plots failed: {type(error).__name__}: {error}")
            metrics["plots"] = []
    _write_json(run_dir / "metrics.json", metrics)
    logger.info(f"{split} metrics: {_summary_line(metrics)}")
    logger.info(f"wrote {run_dir / 'metrics.json'}")
    return metrics


def _epoch_line(entry: dict, epochs: int, improved: bool) -> str:
    parts = [f"epoch {entry['epoch']}/{epochs}", f"train loss {entry['train_loss']:.4g}"]
    for key in ("train_accuracy", "val_loss", "val_accuracy", "val_MAPE"):
        if key in entry:
            parts.append(f"{key.replace('_', ' ')} {entry[key]:.4g}")
    parts.append(f"{entry['seconds']:.1f} s")
    return ", ".join(parts) + (" *" if improved else "")


@torch.no_grad()
def _validate(model, dataset, indices, device, loss_name, target_stats, task, feature_stats=None) -> dict:
    """Mean validation loss and metric over shapes (each shape counts once)."""
    from zernet import metrics as zmetrics

    model.eval()
    losses, scores = [], []
    for i in indices:
        batch = _Batch([dataset[i]], device, target_stats, feature_stats)
        output = model(batch.features, batch.geometry)
        losses.append(_loss(loss_name, output, batch.target, target_stats).item())
        if task == "classification":
            scores.append(zmetrics.accuracy(output.argmax(dim=1), batch.target))
        else:
            pred = _unstandardise(output.reshape(-1), target_stats)
            scores.append(zmetrics.regression_scores(pred, dataset[i].target)["MAPE"])
    model.train()
    key = "val_accuracy" if task == "classification" else "val_MAPE"
    return {"val_loss": float(np.mean(losses)), key: float(np.mean(scores))}


def _standardise(target: torch.Tensor, target_stats: dict) -> torch.Tensor:
    """Target in the units the network is trained in (see :func:`_target_stats`)."""
    target = target.float()
    if target_stats.get("transform", "none") == "log":
        target = torch.log(target)
    return (target - target_stats["mean"]) / target_stats["std"]


def _unstandardise(values: torch.Tensor, target_stats: dict | None) -> torch.Tensor:
    """Inverse of :func:`_standardise`: network output back to the target's units."""
    return _untransform(_destandardise(values, target_stats), target_stats)


def _destandardise(values: torch.Tensor, target_stats: dict | None) -> torch.Tensor:
    """Network output -> transformed target units (e.g. log stress): undo the standardisation only."""
    if target_stats is None:
        return values
    return values * target_stats["std"] + target_stats["mean"]


def _untransform(values: torch.Tensor, target_stats: dict | None) -> torch.Tensor:
    """Transformed target units -> the target's units (undo ``target_transform``)."""
    if target_stats is not None and target_stats.get("transform", "none") == "log":
        return torch.exp(values)
    return values


def _write_json(path: Path, data: dict) -> None:
    def default(value):
        if isinstance(value, (np.integer,)):
            return int(value)
        if isinstance(value, (np.floating,)):
            return float(value)
        if isinstance(value, np.ndarray):
            return value.tolist()
        raise TypeError(f"not JSON serialisable: {type(value).__name__}")

    text = json.dumps(data, indent=2, default=default, allow_nan=True)
    atomic_write_bytes(path, (text + "\n").encode("utf-8"))


# --------------------------------------------------------------------------------------------------------
# Evaluation and prediction
# --------------------------------------------------------------------------------------------------------


@torch.no_grad()
def _predict_record(members: Sequence[tuple], record, device) -> tuple[np.ndarray, np.ndarray | None]:
    """(prediction, probabilities) for one record: class index and softmax per vertex, or the value.

    ``members`` is a list of ``(model, checkpoint)``. With several (an ensemble) the prediction is made from
    the mean of their softmax probabilities (classification), or of their outputs in the transformed target
    units (regression; with ``target_transform: log`` a geometric mean of the values), which for one member
    is that member's own prediction.
    """
    task = members[0][1]["task"]
    outputs = []
    for model, checkpoint in members:
        model.eval()
        batch = _Batch([record], device, None, checkpoint.get("feature_stats"))
        output = model(batch.features, batch.geometry).float()
        if task == "classification":
            outputs.append(torch.softmax(output, dim=1))
        else:
            outputs.append(_destandardise(output.reshape(-1), checkpoint["target_stats"]))
    mean = outputs[0] if len(outputs) == 1 else torch.stack(outputs).mean(dim=0)
    if task == "classification":
        return mean.argmax(dim=1).cpu().numpy(), mean.cpu().numpy()
    return _untransform(mean, members[0][1]["target_stats"]).cpu().numpy(), None


def _evaluate_model(members: Sequence[tuple], dataset, indices: Sequence[int], device, progress: bool,
                    keep: int = 3) -> tuple[dict, list[dict]]:
    """Metrics of the model (or ensemble) ``members`` (a list of ``(model, checkpoint)``, see
    :func:`_predict_record`) on the shapes at ``indices`` and the predictions of the first ``keep``."""
    from tqdm.auto import tqdm

    from zernet import metrics as zmetrics

    checkpoint = members[0][1]
    task = checkpoint["task"]
    correspondence = task == "classification" and checkpoint.get("correspondence", False)
    kind = "correspondence" if correspondence else ("segmentation" if task == "classification" else "regression")
    per_shape: dict[str, dict] = {}
    kept: list[dict] = []
    errors_all, confusion = [], None
    label_counts = None
    for position, i in enumerate(tqdm(indices, desc="evaluating", unit="shape", leave=False,
                                      disable=not progress)):
        record = dataset[i]
        if record.target is None:
            raise ValueError(f"shape {record.name} has no ground truth to evaluate against")
        pred, _ = _predict_record(members, record, device)
        target = np.asarray(record.target)
        errors = None
        if kind == "correspondence":
            errors = zmetrics.geodesic_errors(record.surface, pred, target)
            errors_all.append(errors)
            scores = zmetrics.correspondence_scores(errors)
            per_shape[record.name] = {k: v for k, v in scores.items() if not k.startswith("curve_")}
        elif kind == "segmentation":
            n_classes = int(checkpoint["num_classes"])
            shape_confusion = zmetrics.confusion_matrix(pred, target, n_classes)
            confusion = shape_confusion if confusion is None else confusion + shape_confusion
            counts = np.bincount(target, minlength=n_classes)
            label_counts = counts if label_counts is None else label_counts + counts
            per_shape[record.name] = {"accuracy": zmetrics.accuracy(pred, target)}
            errors = (pred != target).astype(np.float64)
        else:
            per_shape[record.name] = zmetrics.regression_scores(pred, target)
            with np.errstate(divide="ignore", invalid="ignore"):
                errors = np.abs(pred - target) / np.abs(target)
        if position < keep:
            kept.append({"name": record.name, "surface": record.surface, "prediction": pred, "target": target,
                         "error": errors})

    result: dict[str, Any] = {"task": task, "kind": kind, "n_shapes": len(indices)}
    if kind == "correspondence":
        scores = zmetrics.correspondence_scores(errors_all)
        result["summary"] = {k: v for k, v in scores.items() if not k.startswith("curve_")}
        result["error_curve"] = {"radii": scores["curve_radii"], "fractions": scores["curve_fractions"]}
        result["baseline"] = {"chance_accuracy": 1.0 / float(checkpoint["num_classes"])}
    elif kind == "segmentation":
        result["summary"] = zmetrics.segmentation_scores(confusion=confusion)
        result["baseline"] = {"majority_class_accuracy": float(label_counts.max() / label_counts.sum())}
    else:
        aggregated = zmetrics.aggregate_scores(per_shape)
        result["summary"] = aggregated["mean"]
        result["summary_std"] = aggregated["std"]
        stats = checkpoint.get("target_stats")
        if stats is not None:
            # The honest reference: predicting the training mean (of the trained units) everywhere.
            mean = float(_unstandardise(torch.zeros(1), stats))
            constant = [zmetrics.regression_scores(np.full(len(dataset.target(i)), mean), dataset.target(i))
                        for i in indices]
            result["baseline"] = {"training_mean_MAPE": float(np.mean([c["MAPE"] for c in constant])),
                                  "training_mean_RRMSE": float(np.mean([c["RRMSE"] for c in constant]))}
    result["per_shape"] = per_shape
    return result, kept


def _summary_line(metrics: dict) -> str:
    summary = metrics.get("summary", {})
    keys = {"correspondence": ("accuracy", "within_0.025", "within_0.05", "mean_geodesic_error"),
            "segmentation": ("accuracy", "mean_class_accuracy", "mean_iou"),
            "regression": ("MAPE", "RRMSE", "PCC", "HR10", "HR20", "HR30")}.get(metrics.get("kind"), ())
    parts = [f"{key} {summary[key]:.4f}" for key in keys if key in summary]
    for key, value in metrics.get("baseline", {}).items():
        parts.append(f"(baseline {key} {value:.4f})")
    return ", ".join(parts)


def _write_plots(run_dir: Path, history: list[dict], metrics: dict, kept: list[dict], dataset,
                 renders: int) -> list[str]:
    """Training curves, the error curve (correspondence) and renders of a few test shapes; returns paths."""
    from zernet import viz

    plot_dir = run_dir / "plots"
    plot_dir.mkdir(exist_ok=True)
    written = []
    if history:
        written.append(viz.plot_training_curves(history, plot_dir / "training_curves.png",
                                                title=f"training ({metrics['kind']})"))
    if "error_curve" in metrics:
        curve = metrics["error_curve"]
        written.append(viz.plot_error_curve({"zernet (test)": (curve["radii"], curve["fractions"])},
                                            plot_dir / "error_curve.png"))
    class_names = getattr(dataset, "info", {}).get("class_names")
    for item in kept[:renders]:
        path = plot_dir / f"test_{_safe_name(item['name'])}.png"
        surface, pred, target, error = item["surface"], item["prediction"], item["target"], item["error"]
        if metrics["kind"] == "correspondence":
            # Vertex indices carry no visual meaning: colour each vertex by the height of the vertex it is
            # matched to (prediction) or should be matched to (truth) on the same shape, so a correct map
            # gives two identical pictures.
            height = surface.vertices[:, 1]
            written.append(viz.render_comparison(
                surface, height[pred], height[target], error, path, error_label="geodesic error",
                title=f"{item['name']}: matched vertex height", error_max=0.1))
        elif metrics["kind"] == "segmentation":
            written.append(viz.render_comparison(
                surface, pred, target, error, path, error_label="wrong label", class_names=class_names, error_max=1.0,
                title=f"{item['name']}: {np.mean(pred == target):.1%} correct"))
        else:
            written.append(viz.render_comparison(
                surface, pred, target, np.minimum(error, 1.0), path, error_label="relative error",
                title=f"{item['name']}: MAPE {np.nanmean(error):.3f}", error_max=0.5))
    return [str(p) for p in written]


def _safe_name(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name)[:80]


def evaluate(run_dir_or_checkpoint, dataset=None, split: str = "test", progress: bool = True,
             device: str | None = None) -> dict:
    """Evaluate a trained model (a run folder's ``best.pt``, or any checkpoint file) on one split; given
    several, evaluate their ensemble.

    Args:
        run_dir_or_checkpoint: a run folder or a ``.pt`` checkpoint, or a list of them: an ensemble whose
            prediction averages the members' probabilities or (regression) their outputs in the transformed
            target units (see :func:`_predict_record`). Members must share the task, the classes, the
            preprocessing and the data section (apart from ``data.root``), e.g. the same recipe trained
            with different ``train.seed``.
        dataset: the :class:`~zernet.data.ShapeDataset` to use; by default it is rebuilt (from the cache)
            from the configuration stored in the (first) checkpoint.
        split: ``"test"``, ``"val"``, ``"train"`` or any split the data set defines.
        device: overrides the configured ``train.device``.

    Returns:
        The same metrics dictionary that training writes to ``metrics.json`` (for an ensemble,
        ``checkpoint`` lists the members and ``best_epoch``/``epochs_trained`` are per member).
    """
    many = isinstance(run_dir_or_checkpoint, (list, tuple))
    paths = [_checkpoint_path(p) for p in (run_dir_or_checkpoint if many else [run_dir_or_checkpoint])]
    if not paths:
        raise ConfigError("evaluate needs at least one run folder or checkpoint")
    checkpoints = [load_checkpoint(path) for path in paths]
    _check_ensemble(paths, checkpoints)
    config = checkpoints[0]["config"]
    device = resolve_device(device or config["train"]["device"])
    if dataset is None:
        dataset = build_dataset(config, progress=progress)
    if split not in dataset.splits:
        raise ConfigError(f"the data set has no split {split!r} (it has {', '.join(sorted(dataset.splits))})")
    indices = dataset.splits[split]
    if not indices:
        raise ConfigError(f"split {split!r} of the data set is empty")
    members = []
    for checkpoint in checkpoints:
        model = _build_model(checkpoint["model_spec"]).to(device)
        model.load_state_dict(checkpoint["model"])
        members.append((model, checkpoint))
    metrics, _ = _evaluate_model(members, dataset, indices, device, progress, keep=0)
    best_epochs = [c["state"]["best_epoch"] for c in checkpoints]
    epochs = [c["state"]["epoch"] for c in checkpoints]
    metrics.update({"split": split, "checkpoint": [str(p) for p in paths] if many else str(paths[0]),
                    "best_epoch": best_epochs if many else best_epochs[0],
                    "epochs_trained": epochs if many else epochs[0]})
    return metrics


def _check_ensemble(paths: Sequence[Path], checkpoints: Sequence[dict]) -> None:
    """Ensemble members must predict the same thing from the same inputs: say which one differs and how."""
    def data_section(checkpoint):
        return {k: v for k, v in checkpoint["config"]["data"].items() if k != "root"}

    first = checkpoints[0]
    for path, checkpoint in zip(paths[1:], checkpoints[1:]):
        for what, value in (("task", lambda c: c["task"]), ("number of classes", lambda c: c["num_classes"]),
                            ("preprocessing", lambda c: c["preprocess"]), ("data section", data_section)):
            if value(checkpoint) != value(first):
                raise ConfigError(f"cannot ensemble {path} with {paths[0]}: their {what} differs "
                                  f"({value(checkpoint)!r} vs {value(first)!r})")


def predict(checkpoint: str | Path, surface, probabilities: bool = False, device: str | None = None,
            cache_dir: str | Path | None = None, progress: bool = False):
    """Per-vertex predictions of a trained model on a new surface.

    Args:
        checkpoint: a run folder (its ``best.pt``) or a checkpoint file.
        surface: a :class:`~zernet.surface.Surface` or a path to a mesh / point-cloud file. It is
            preprocessed exactly like the training shapes (area normalisation, features, patch operators).
        probabilities: classification only — also return the (N, C) softmax probabilities.

    Returns:
        (N,) int64 class indices or (N,) float32 values (regression: in the surface's own units — the model
        predicts at the training area, and a target of area exponent e is divided by ``scale ** (2 e)``);
        with ``probabilities=True`` a tuple (prediction, probabilities).
    """
    from zernet.data import prepare_record
    from zernet.patches import PatchConfig
    from zernet.surface import load_surface

    path = _checkpoint_path(checkpoint)
    checkpoint = load_checkpoint(path)
    config, spec = checkpoint["config"], checkpoint["preprocess"]
    if not hasattr(surface, "vertices"):
        surface = load_surface(surface)
    record = prepare_record(
        surface,
        [PatchConfig(**c) for c in spec["patch_configs"]],
        cache_dir=config["cache_dir"] if cache_dir is None else cache_dir,
        target_area=spec["area"],
        feature_kind=spec["feature_kind"],
    )
    device = resolve_device(device or config["train"]["device"])
    model = _build_model(checkpoint["model_spec"]).to(device)
    model.load_state_dict(checkpoint["model"])
    pred, probs = _predict_record([(model, checkpoint)], record, device)
    if checkpoint["task"] == "classification":
        pred = pred.astype(np.int64)
    else:
        exponent = float(checkpoint.get("target_exponent", 0.0))  # older checkpoints: area-normalised
        pred = (pred / record.scale ** (2 * exponent)).astype(np.float32)
    if probabilities:
        if probs is None:
            raise ValueError("probabilities exist only for classification models")
        return pred, probs.astype(np.float32)
    return pred
