"""Data sets: preprocessed surfaces with their targets, patch operators and splits.

Entry point for training and the command line::

    dataset = load_dataset(kind, options=LoaderOptions(patch_configs=..., cache_dir=..., workers=...,
                                                       seed=0, n_val=0.1, feature_kind="xyz", ...),
                           **kind_arguments)

:class:`~zernet.data.options.LoaderOptions` holds the options every data set shares (patch settings, cache,
features, seed and validation count, workers, on_error, repair, progress); ``kind_arguments`` are the
arguments particular to the kind's loader (:data:`DATASET_KINDS`):

- ``"synthetic"`` / ``"synthetic-parts"``: built-in creatures, part segmentation (4 classes);
  ``"synthetic-curvature"``: the same creatures, mean-curvature regression. Arguments of
  :func:`~zernet.data.synthetic.make_synthetic_dataset`: n_shapes, n_vertices, rotate, test_fraction, area
  (``task`` is set by the kind, or give ``task=`` with "synthetic").
- ``"faust"``: :func:`~zernet.data.faust.load_faust` — root (required), train_indices, test_indices,
  n_vertices, area.
- ``"segmentation"``: :func:`~zernet.data.segmentation.load_segmentation` — meshes (required), labels,
  num_classes, class_names, label_base, label_kind, test, test_fraction, area.
- ``"bodies"``: :func:`~zernet.data.bodies.dataset.load_bodies` — generated human bodies (extra
  ``zernet[bodies]``), no files written: task ("segmentation" | "correspondence"), count, n_test, topology,
  poses, body_seed, area.
- ``"aneurysm"``: :func:`~zernet.data.regression.load_aneurysm` — root (required), field, test, area.
- ``"regression"``: :func:`~zernet.data.regression.load_regression` — root (required), field,
  target_exponent, test, test_fraction, area.

Every kind takes ``forms`` (:mod:`~zernet.data.training_forms`): its training shapes are also trained on
remeshed, decimated, as point clouds or scanned from one side, their per-vertex targets carried over.

Without ``options``, every shared option is also accepted as a keyword, together with ``val_fraction``
(default 0.1) and ``val_count`` (a count, overrides ``val_fraction``) for ``n_val``, and ``area=None`` then
means the kind's default area (FAUST/segmentation/bodies 15000, aneurysm 100, synthetic 1000; the generic
regression default keeps the files' scale) — the interface the run configuration uses. An argument the kind
does not take raises TypeError naming it and listing what the kind takes.
"""

from __future__ import annotations

import inspect
import warnings
from collections.abc import Callable

from zernet.data.bodies.dataset import load_bodies
from zernet.data.dataset import DatasetError, ShapeDataset, ShapeRecord, carve_validation
from zernet.data.faust import load_faust
from zernet.data.features import FEATURE_PARTS, compute_features, default_features
from zernet.data.options import ON_ERROR_CHOICES, SHARED_OPTIONS, LoaderOptions
from zernet.data.preprocess import PreprocessError, SkippedShapesWarning, build_dataset, prepare_record
from zernet.data.regression import load_aneurysm, load_regression
from zernet.data.segmentation import load_segmentation
from zernet.data.source import ShapeSource
from zernet.data.synthetic import make_synthetic_dataset

__all__ = [
    "DATASET_KINDS",
    "ON_ERROR_CHOICES",
    "data_option_names",
    "load_dataset",
    "LoaderOptions",
    "ShapeRecord",
    "ShapeDataset",
    "ShapeSource",
    "DatasetError",
    "PreprocessError",
    "SkippedShapesWarning",
    "FEATURE_PARTS",
    "build_dataset",
    "prepare_record",
    "default_features",
    "compute_features",
    "carve_validation",
]

#: The loader of each data set kind.
LOADERS: dict[str, Callable[..., ShapeDataset]] = {
    "synthetic": make_synthetic_dataset,
    "synthetic-parts": make_synthetic_dataset,
    "synthetic-curvature": make_synthetic_dataset,
    "faust": load_faust,
    "segmentation": load_segmentation,
    "bodies": load_bodies,
    "aneurysm": load_aneurysm,
    "regression": load_regression,
}
DATASET_KINDS = tuple(LOADERS)
# The synthetic kinds that fix the task.
_SYNTHETIC_TASKS = {"synthetic-parts": "segmentation", "synthetic-curvature": "regression"}
# Keywords of the configuration interface that become LoaderOptions.n_val.
_VALIDATION_KEYWORDS = ("val_fraction", "val_count")


def load_dataset(kind: str, options: LoaderOptions | None = None, **arguments) -> ShapeDataset:
    """Build (preprocess and cache) the data set of ``kind``; see the module docstring for the arguments."""
    if kind not in LOADERS:
        raise DatasetError(f"unknown data set kind {kind!r}; choose one of {', '.join(DATASET_KINDS)}")
    if kind in _SYNTHETIC_TASKS:
        if "task" in arguments:
            raise TypeError(f"data kind {kind!r} fixes the task; use kind 'synthetic' with task=...")
        arguments["task"] = _SYNTHETIC_TASKS[kind]
    if options is None:
        options, arguments = _options_from_keywords(arguments)
    elif not isinstance(options, LoaderOptions):
        raise TypeError(f"options must be a LoaderOptions, got {type(options).__name__}")
    else:
        shared = sorted(set(arguments) & (set(SHARED_OPTIONS) | set(_VALIDATION_KEYWORDS)))
        if shared:
            raise TypeError(
                f"{', '.join(shared)}: give shared options inside options=LoaderOptions(...), not as keywords beside it"
            )
    loader = LOADERS[kind]
    accepted = set(inspect.signature(loader).parameters) - {"options"}
    unknown = sorted(set(arguments) - accepted)
    if unknown:
        takes = sorted(accepted - ({"task"} if kind in _SYNTHETIC_TASKS else set()))
        raise TypeError(
            f"unknown option(s) {', '.join(unknown)} for data kind {kind!r} (it takes: "
            f"{', '.join(takes)}; and the shared options {', '.join(SHARED_OPTIONS)})"
        )
    return loader(**arguments, options=options)


def data_option_names(kind: str) -> tuple[str, ...]:
    """The keys a run configuration's ``data`` section may pass to the loader of ``kind``, besides the ones
    the run sets itself (``seed``, ``val_fraction``, ``val_count``, ``on_error``): the loader's own arguments
    (except ``area``, which is ``patch.area``), ``features``, ``repair``, ``workers`` and ``forms``. Empty
    for an unknown kind."""
    if kind not in LOADERS:
        return ()
    own = set(inspect.signature(LOADERS[kind]).parameters) - {"options", "area"}
    if kind in _SYNTHETIC_TASKS:
        own.discard("task")
    return tuple(sorted(own | {"features", "repair", "workers", "forms"}))


def _options_from_keywords(arguments: dict) -> tuple[LoaderOptions, dict]:
    """Split the configuration interface's keywords into LoaderOptions and the loader's own arguments."""
    arguments = dict(arguments)
    if "strict" in arguments:  # the former name of on_error
        strict = arguments.pop("strict")
        warnings.warn(
            "the data option 'strict' is deprecated: use on_error='raise' (strict true) or 'skip' (strict false)",
            FutureWarning,
            stacklevel=3,
        )
        arguments.setdefault("on_error", "raise" if strict else "skip")
    shared = {name: arguments.pop(name) for name in SHARED_OPTIONS if name in arguments}
    val_fraction = arguments.pop("val_fraction", 0.1)
    val_count = arguments.pop("val_count", None)
    shared.setdefault("n_val", val_count if val_count is not None else float(val_fraction))
    if "area" in arguments and arguments["area"] is None:
        del arguments["area"]  # the kind's default area
    return LoaderOptions(**shared), arguments
