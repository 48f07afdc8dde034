"""What a run is made of: the data set, and the checks of its model before any data is loaded.

:func:`build_dataset` takes a whole run configuration (what a user holds) and hands its ``data``,
``patch`` and ``cache_dir`` parts to :func:`load_data`; the model is built from a *spec* (name, channel
counts, options) that the checkpoint stores (:mod:`zernet.inference.spec`), so it is rebuilt anywhere.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import torch

from zernet.data import DatasetError, load_dataset
from zernet.data.features import feature_channels, needs_patch_operators
from zernet.geometry import FixedScale
from zernet.inference.spec import model_spec
from zernet.io_utils import plain
from zernet.nn.models import build_model, reads_patch_operators
from zernet.operators import PatchConfig
from zernet.training.config import ConfigError, DataSection, PatchSection, RunConfig, parse_config

__all__ = [
    "build_dataset",
    "load_data",
    "needs_operators",
    "check_model_config",
    "is_correspondence",
    "preprocess_spec",
]


def build_dataset(
    config: Mapping[str, Any] | RunConfig,
    progress: bool = True,
    workers: int | None = None,
    on_error: str | None = None,
):
    """The :class:`~zernet.data.ShapeDataset` a run configuration describes (preprocessed and cached);
    ``on_error`` overrides ``data.on_error``."""
    config = parse_config(config)
    return load_data(
        config.data,
        config.patch,
        config.cache_dir,
        progress=progress,
        workers=workers,
        on_error=on_error,
        patch_operators=needs_operators(config),
    )


def needs_operators(config: RunConfig) -> bool:
    """Whether a run's shapes need patch operators: its model reads them, or its input features are computed
    from them. A FeaStNet run on ``xyz`` needs none, so it skips the geodesic patches (minutes per hundred
    bodies, and 150 MB of cache per body at FAUST size) that it would never read."""
    try:
        model_reads = reads_patch_operators(config.model.name)
    except ValueError:  # an unknown model name is reported when the model is built
        model_reads = True
    try:
        features_read = needs_patch_operators(config.data.options.get("features", "xyz"))
    except DatasetError as error:
        raise ConfigError(f"data.features: {error}") from None
    return model_reads or features_read


def load_data(
    data: DataSection,
    patch: PatchSection,
    cache_dir: str | None,
    progress: bool = True,
    workers: int | None = None,
    on_error: str | None = None,
    patch_operators: bool = True,
):
    """Hand ``data.kind`` to :func:`zernet.data.load_dataset` with the patch scales, ``patch.area`` (or
    ``patch.scale``),
    ``cache_dir``, ``data.seed``, ``data.on_error`` (or ``on_error`` when given), ``data.val_fraction``/
    ``data.val_count`` (unless null: the loader's default) and ``data.features`` (as ``feature_kind``);
    every other ``data`` key is a loader option passed by name (``root``, ``test``, ...).
    ``patch_operators=False`` builds none (:func:`needs_operators`)."""
    options: dict[str, Any] = {
        "seed": data.seed,
        "on_error": on_error or data.on_error,
        "patch_operators": patch_operators,
    }
    for key in ("val_fraction", "val_count"):
        if getattr(data, key) is not None:
            options[key] = getattr(data, key)
    options.update(data.options)
    if "features" in options:
        options["feature_kind"] = options.pop("features")
    if workers is not None or "workers" not in options:
        options["workers"] = workers
    try:
        return load_dataset(
            data.kind,
            patch_configs=patch.patch_configs(),
            area=patch.size(),
            cache_dir=cache_dir,
            progress=progress,
            **options,
        )
    except TypeError as error:
        # An option the loader does not take: a configuration problem under data.
        raise ConfigError(f"data (kind {data.kind}): {error}") from None


def check_model_config(config: RunConfig, in_channels: int | None = None, out_channels: int | None = None) -> None:
    """Build the configured model on the meta device (no memory, no data): a bad ``model`` option fails
    here, before any shape is loaded, with a :class:`ConfigError` naming the option and its value.

    The channel counts default to what the configuration implies (features and patch degree; the class
    count or 1); they do not change which options a model accepts.
    """
    degrees = [int(scale.get("n_max", 5)) for scale in config.patch.scales] or [5]
    if in_channels is None:
        try:
            in_channels = feature_channels(config.data.options.get("features", "xyz"), degrees)
        except DatasetError as error:
            raise ConfigError(f"data.features: {error}") from None
    if out_channels is None:
        out_channels = int(config.data.options.get("num_classes", 2)) if _is_classification(config) else 1
    spec = model_spec(config.model, in_channels, out_channels, [PatchConfig(r0=1.0, n_max=n) for n in degrees])
    try:
        with torch.device("meta"):
            build_model(spec["name"], spec["in_channels"], spec["out_channels"], **spec["options"])
    except Exception as error:  # any failure of the constructor is a problem of the model options
        # The options the message is about, when it names them; else every option given.
        named = {k: v for k, v in config.model.options.items() if k in str(error)} or config.model.options
        given = ", ".join(f"model.{key}={value!r}" for key, value in named.items()) or "defaults"
        raise ConfigError(
            f"model {config.model.name!r} cannot be built from its options ({given}): {type(error).__name__}: {error}"
        ) from None


def _is_classification(config: RunConfig) -> bool:
    task = config.data.options.get("task", "segmentation")
    return config.data.kind in ("faust", "segmentation", "synthetic-parts") or (
        config.data.kind == "synthetic" and task == "segmentation"
    )


def is_correspondence(dataset, data_kind: str) -> bool:
    """Correspondence = classification whose class is the vertex index of a shared template."""
    flag = getattr(dataset, "correspondence", None)
    if flag is not None:
        return bool(flag)
    return data_kind == "faust"


def preprocess_spec(dataset) -> dict:
    """What :func:`zernet.inference.predict.predict` needs to preprocess a new surface like the training shapes:
    the area every shape was scaled to, or the fixed factor applied instead (``unit_scale``)."""
    fixed = isinstance(dataset.target_area, FixedScale)
    return {
        "patch_configs": [plain(dataclasses.asdict(c)) for c in dataset.patch_configs],
        "area": None if dataset.target_area is None or fixed else float(dataset.target_area),
        "unit_scale": float(dataset.target_area.factor) if fixed else None,
        "feature_kind": str(dataset.feature_kind),
        "class_names": plain(dataset.info.get("class_names")),
    }
