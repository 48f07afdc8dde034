"""The loader options every data set shares: :class:`LoaderOptions`.

Each loader (:func:`~zernet.data.faust.load_faust`, :func:`~zernet.data.segmentation.load_segmentation`,
:func:`~zernet.data.regression.load_aneurysm`, :func:`~zernet.data.regression.load_regression`,
:func:`~zernet.data.synthetic.make_synthetic_dataset`) takes the arguments particular to its data set plus
``options: LoaderOptions``. The fields whose default differs between data sets (``patch_configs``,
``n_val``) are None here, meaning "the data set's default", which each loader's docstring gives.

Bad shapes: ``on_error="raise"`` (the default, for every data set) tries every shape, then stops with a
:class:`~zernet.data.preprocess.PreprocessError` listing each one that failed and why; ``on_error="skip"``
leaves them out (``dataset.failures`` lists them). The former ``strict=True/False`` is ``on_error``
``"raise"``/``"skip"``.

The target ``area`` is not a shared option: its default is a property of each data set (FAUST 15000,
aneurysm 100, ...), and for a loader None means "keep the files' scale".
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from typing import Any

from zernet.data.dataset import DatasetError
from zernet.data.features import feature_parts, needs_patch_operators
from zernet.data.preprocess import as_patch_configs
from zernet.data.training_forms import check_form_rates

__all__ = ["LoaderOptions", "SHARED_OPTIONS", "ON_ERROR_CHOICES"]

#: What a shape that fails to load or preprocess does: stop the loader (after trying every shape), or be left out.
ON_ERROR_CHOICES = ("raise", "skip")


@dataclass(frozen=True)
class LoaderOptions:
    """How a data set is preprocessed, cached, featurised and split.

    Attributes:
        patch_configs: :class:`~zernet.operators.patch.PatchConfig` (or dicts), one per scale; None or empty: the
            data set's default (segmentation and generic regression have none and require it).
        cache_dir: folder of the preprocessing cache (shapes, patch operators, membrane stresses).
        feature_kind: model input, parts of :data:`~zernet.data.features.FEATURE_PARTS` joined by "+".
        seed: seeds the validation split (and the test split where a loader draws one, and the synthetic
            shapes).
        n_val: validation shapes carved from the training ones, a count or a fraction in (0, 1); None: the
            data set's default.
        workers: preprocessing processes; None: one per CPU; 0 or 1: in this process.
        on_error: what a shape that fails to load or preprocess does: ``"raise"`` (every shape is tried,
            then an error lists each failure) or ``"skip"`` (it is left out and listed in
            ``dataset.failures``).
        repair: merge duplicate vertices and drop degenerate faces while validating the surfaces.
        progress: show a progress bar while preprocessing.
        patch_operators: build the patch operators (False: every record's geometry holds only the mesh
            edges, for a model that reads nothing else, such as FeaStNet: no geodesic patches are computed
            or read; the features must not need them).
        forms: the training shapes' forms trained on beside them, {form name: copies per training shape}
            (``{"cloud": 0.25}``: a point cloud of a quarter of them), drawn with ``seed``; empty: none.
            See :mod:`zernet.data.training_forms`.
    """

    patch_configs: tuple | None = None
    cache_dir: str | os.PathLike = ".zernet-cache"
    feature_kind: str = "xyz"
    seed: int = 0
    n_val: int | float | None = None
    workers: int | None = None
    on_error: str = "raise"
    repair: bool = False
    progress: bool = True
    patch_operators: bool = True
    forms: Mapping[str, float] = field(default_factory=dict)

    def __post_init__(self):
        # Checked here, before any file is read: unknown names, negative rates, a missing package.
        object.__setattr__(self, "forms", check_form_rates(self.forms))
        configs = self.patch_configs
        # One PatchConfig, a dict or a list of either; empty means "the data set's default", like None.
        object.__setattr__(self, "patch_configs", tuple(as_patch_configs(configs)) if configs else None)
        feature_parts(self.feature_kind)  # an unknown feature kind fails here, before any file is read
        if not self.patch_operators and needs_patch_operators(self.feature_kind):
            raise DatasetError(
                f"features {self.feature_kind!r} are computed from the patch operators, "
                "which patch_operators=False leaves out"
            )
        if self.on_error not in ON_ERROR_CHOICES:
            raise DatasetError(f"on_error must be one of {', '.join(ON_ERROR_CHOICES)}, got {self.on_error!r}")

    def with_defaults(self, *, n_val: int | float, patch_configs=None) -> LoaderOptions:
        """These options with a data set's defaults filled in where a field is None."""
        return replace(
            self, n_val=n_val if self.n_val is None else self.n_val, patch_configs=self.patch_configs or patch_configs
        )

    def build_arguments(self) -> dict[str, Any]:
        """The keyword arguments of :func:`~zernet.data.preprocess.build_dataset` these options give."""
        if self.n_val is None:
            raise ValueError("LoaderOptions.build_arguments needs n_val: call with_defaults first")
        return {
            "patch_configs": self.patch_configs if self.patch_operators else (),
            "cache_dir": self.cache_dir,
            "n_val": self.n_val,
            "seed": self.seed,
            "feature_kind": self.feature_kind,
            "workers": self.workers,
            "on_error": self.on_error,
            "repair": self.repair,
            "progress": self.progress,
            "forms": self.forms,
        }


#: Names of the shared options (the fields of :class:`LoaderOptions`).
SHARED_OPTIONS = tuple(field.name for field in fields(LoaderOptions))
