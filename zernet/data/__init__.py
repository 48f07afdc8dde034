"""Data sets: preprocessed surfaces with their targets, patch operators and splits.

Entry point for training and the command line::

    dataset = load_dataset(kind, patch_configs=..., area=..., cache_dir=..., progress=..., workers=...,
                           seed=0, val_fraction=0.1, val_count=None, **loader_options)

Kinds (:data:`DATASET_KINDS`) and their loader options:

- ``"synthetic"`` / ``"synthetic-parts"``: built-in creatures, part segmentation (4 classes);
  ``"synthetic-curvature"``: the same creatures, mean-curvature regression. Options of
  :func:`~zernet.data.synthetic.make_synthetic_dataset`: n_shapes, n_vertices, rotate, test_fraction,
  feature_kind (``task`` is set by the kind, or give ``task=`` with "synthetic").
- ``"faust"``: :func:`~zernet.data.faust.load_faust` — root (required), train_indices, test_indices, ...
- ``"segmentation"``: :func:`~zernet.data.segmentation.load_segmentation` — meshes (required), labels,
  num_classes, label_base, label_kind, test, test_fraction, ...
- ``"aneurysm"``: :func:`~zernet.data.regression.load_aneurysm` — root (required), field, test, ...
- ``"regression"``: :func:`~zernet.data.regression.load_regression` — root (required), field,
  target_exponent, test, test_fraction, ...

``patch_configs`` empty or None uses the kind's default patch settings; ``area`` None uses the kind's
default area (FAUST/segmentation 15000, aneurysm 100, synthetic 1000; the generic regression default keeps
the files' scale). ``val_count`` (a count) overrides ``val_fraction``. An option a loader does not take
raises TypeError.
"""

from __future__ import annotations

import inspect

from zernet.data.base import (
    FEATURE_PARTS,
    DatasetError,
    ShapeDataset,
    ShapeRecord,
    carve_validation,
    compute_features,
    default_features,
)
from zernet.data.preprocess import PreprocessError, ShapeSource, build_dataset, prepare_record

__all__ = [
    "DATASET_KINDS",
    "load_dataset",
    "ShapeRecord",
    "ShapeDataset",
    "ShapeSource",
    "DatasetError",
    "PreprocessError",
    "FEATURE_PARTS",
    "build_dataset",
    "prepare_record",
    "default_features",
    "compute_features",
    "carve_validation",
]

DATASET_KINDS = ("synthetic", "synthetic-parts", "synthetic-curvature", "faust", "segmentation", "aneurysm",
                 "regression")


def load_dataset(
    kind: str,
    patch_configs=None,
    area: float | None = None,
    cache_dir=".zernet-cache",
    progress: bool = True,
    workers: int | None = None,
    seed: int = 0,
    val_fraction: float = 0.1,
    val_count: int | None = None,
    **options,
) -> ShapeDataset:
    """Build (preprocess and cache) the data set of ``kind``; see the module docstring for the options."""
    from zernet.data import faust, regression, segmentation, synthetic

    n_val = val_count if val_count is not None else float(val_fraction)
    common = {"patch_configs": patch_configs or None, "cache_dir": cache_dir, "progress": progress,
              "workers": workers, "seed": seed, "n_val": n_val}
    if kind in ("synthetic", "synthetic-parts", "synthetic-curvature"):
        if kind != "synthetic" and "task" in options:
            raise TypeError(f"data kind {kind!r} fixes the task; use kind 'synthetic' with task=...")
        task = options.pop("task", "regression" if kind == "synthetic-curvature" else "segmentation")
        function, extra = synthetic.make_synthetic_dataset, {"task": task, "area": area}
    elif kind == "faust":
        function, extra = faust.load_faust, ({"area": area} if area is not None else {})
    elif kind == "segmentation":
        function, extra = segmentation.load_segmentation, ({"area": area} if area is not None else {})
    elif kind == "aneurysm":
        function, extra = regression.load_aneurysm, ({"area": area} if area is not None else {})
    elif kind == "regression":
        function, extra = regression.load_regression, {"area": area}
    else:
        raise DatasetError(f"unknown data set kind {kind!r}; choose one of {', '.join(DATASET_KINDS)}")
    accepted = set(inspect.signature(function).parameters)
    unknown = sorted(set(options) - accepted)
    if unknown:
        raise TypeError(f"unknown option(s) {', '.join(unknown)} for data kind {kind!r} "
                        f"(it takes: {', '.join(sorted(accepted - set(common) - {'area', 'task'}))})")
    return function(**{**common, **extra, **options})
