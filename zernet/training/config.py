"""The run configuration: typed, checked sections read from YAML, with ``--set key=value`` overrides.

A configuration file has five sections and one top-level key (see ``configs/*.yaml``)::

    data:   the data set (kind, split seed, validation share, the bad-shape policy on_error: raise|skip,
            and the loader's own options, checked against the kind's loader)
    patch:  area normalisation and one patch setting per scale
    model:  the model name and the options of its constructor
    train:  optimisation, early stopping, device and precision
    eval:   pictures written after training
    cache_dir: where preprocessed patch operators are kept

:func:`parse_config` turns a mapping into a :class:`RunConfig` of frozen dataclasses, one per section; each
checks its values when it is made, so a bad value fails before any data is loaded, with a
:class:`ConfigError` that names the key, the value and what is expected. ``data`` and ``model`` also carry
keys the loop does not interpret (``options``): they are passed by name to the data-set loader and to the
model's constructor, which reject what they do not know; the types of the common ones are checked here.

:meth:`RunConfig.to_dict` gives back the plain mapping that ``config.yaml`` and the checkpoints store (the
defaults filled in, keys in a fixed order), and ``parse_config(config.to_dict()) == config``.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import re
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import yaml

from zernet.data import DATASET_KINDS, ON_ERROR_CHOICES, DatasetError, data_option_names
from zernet.data.faust import registration_numbers
from zernet.data.training_forms import check_form_rates
from zernet.geometry import FixedScale
from zernet.inference.errors import ConfigError
from zernet.nn.models import available_models
from zernet.operators import PatchConfig

__all__ = [
    "ConfigError",
    "DataSection",
    "PatchSection",
    "ModelSection",
    "TrainSection",
    "EvalSection",
    "RunConfig",
    "DEFAULT_CONFIG",
    "LOSSES",
    "TARGET_TRANSFORMS",
    "LR_SCHEDULES",
    "PRECISIONS",
    "RESIDENCY_LEVELS",
    "AUGMENT_ROTATIONS",
    "load_config",
    "apply_overrides",
    "parse_config",
    "read_config",
    "resolve_config",
]

LOSSES = ("auto", "cross_entropy", "mse", "l1", "relative_l1")
TARGET_TRANSFORMS = ("none", "log")
LR_SCHEDULES = ("constant", "cosine")
PRECISIONS = ("float32", "bfloat16")
RESIDENCY_LEVELS = ("auto", "device", "host", "stream")  # see zernet.training.residency
AUGMENT_ROTATIONS = ("none", "vertical", "any")  # see zernet.training.augment


# --------------------------------------------------------------------------------------------------------
# Value rules
# --------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Rule:
    """What one configuration value may be; :meth:`check` raises a :class:`ConfigError` naming the key."""

    kind: str  # "int" | "number" | "str" | "bool" | "int_list" | "number_list" | "str_list" | "names" | "path"
    # | "indices" (a list of integers or "START:STOP")
    optional: bool = False  # None allowed
    minimum: float | None = None  # value >= minimum
    positive: bool = False  # value > 0
    below: float | None = None  # value < below
    choices: tuple[str, ...] = ()

    def expected(self) -> str:
        if self.choices:
            text = f"one of {', '.join(self.choices)}"
        else:
            text = {
                "int": "an integer",
                "number": "a number",
                "str": "a string",
                "bool": "true or false",
                "int_list": "a list of integers",
                "number_list": "a list of numbers",
                "str_list": "a list of strings",
                "names": "a name or a list of names",
                "path": "a folder path",
                "indices": "a list of integers or a quoted range 'START:STOP' (YAML reads an unquoted "
                "10:20 as the number 620)",
            }[self.kind]
        if self.minimum is not None:
            text += f" >= {self.minimum}"
        if self.positive:
            text += " > 0"
        if self.below is not None:
            text += f" and < {self.below}"
        return text + (" or null" if self.optional else "")

    def check(self, key: str, value: Any) -> None:
        if value is None and self.optional:
            return
        if not self._valid(value):
            raise ConfigError(f"{key} must be {self.expected()}, got {value!r}")

    def _valid(self, value: Any) -> bool:
        if self.choices:
            return isinstance(value, str) and value in self.choices
        if self.kind == "bool":
            return isinstance(value, bool)
        if self.kind in ("str", "path"):
            return isinstance(value, str)
        if self.kind == "int_list":
            return isinstance(value, (list, tuple)) and all(_is_int(v) for v in value)
        if self.kind == "number_list":
            return isinstance(value, (list, tuple)) and all(_is_number(v) and math.isfinite(v) for v in value)
        if self.kind == "str_list":
            return isinstance(value, (list, tuple)) and all(isinstance(v, str) for v in value)
        if self.kind == "indices":
            try:
                registration_numbers(value, "")
            except DatasetError:
                return False
            return True
        if self.kind == "names":
            return isinstance(value, str) or (
                isinstance(value, (list, tuple)) and all(isinstance(v, (str, int)) for v in value)
            )
        if self.kind == "int" and not _is_int(value):
            return False
        if self.kind == "number" and not (_is_number(value) and math.isfinite(value)):
            return False
        return (
            (self.minimum is None or value >= self.minimum)
            and (not self.positive or value > 0)
            and (self.below is None or value < self.below)
        )


def _is_int(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _rule(default, kind: str, **limits):
    """A dataclass field with ``default`` whose value must follow ``Rule(kind, **limits)``."""
    return field(default=default, metadata={"rule": Rule(kind, **limits)})


# --------------------------------------------------------------------------------------------------------
# Sections
# --------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Section:
    """A section checks every field against its rule when made; ``from_dict`` refuses unknown keys."""

    NAME: ClassVar[str]
    #: Rules for keys of ``options`` (sections that pass unknown keys through); other options are unchecked.
    OPTION_RULES: ClassVar[dict[str, Rule]] = {}

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            if "rule" in f.metadata:
                f.metadata["rule"].check(f"{self.NAME}.{f.name}", getattr(self, f.name))
        options = getattr(self, "options", None)
        if options is not None:
            object.__setattr__(self, "options", copy.deepcopy(dict(options)))
            for key, rule in self.OPTION_RULES.items():
                if key in self.options:
                    rule.check(f"{self.NAME}.{key}", self.options[key])

    @classmethod
    def _core_names(cls) -> list[str]:
        return [f.name for f in dataclasses.fields(cls) if f.name != "options"]

    @classmethod
    def from_dict(cls, given: Mapping[str, Any]):
        if not isinstance(given, Mapping):
            raise ConfigError(f"config section {cls.NAME!r} must be a mapping, got {type(given).__name__}")
        core = cls._core_names()
        known = {k: copy.deepcopy(v) for k, v in given.items() if k in core}
        others = {k: copy.deepcopy(v) for k, v in given.items() if k not in core}
        if "options" in {f.name for f in dataclasses.fields(cls)}:
            return cls(**known, options=others)
        if others:
            raise ConfigError(f"unknown key {cls.NAME}.{sorted(others)[0]} (known: {', '.join(sorted(core))})")
        return cls(**known)

    def to_dict(self) -> dict[str, Any]:
        """The section as a plain mapping: its fields in order, then the pass-through options."""
        out = {name: copy.deepcopy(getattr(self, name)) for name in self._core_names()}
        out.update(copy.deepcopy(getattr(self, "options", {})))
        return out


@dataclass(frozen=True)
class DataSection(_Section):
    """The data set: ``kind`` and the split; ``options`` go to the loader (``root``, ``features``, ...)."""

    NAME: ClassVar[str] = "data"
    OPTION_RULES: ClassVar[dict[str, Rule]] = {
        "features": Rule("str"),
        "root": Rule("path"),
        "meshes": Rule("path"),
        "labels": Rule("path", optional=True),
        "task": Rule("str"),
        "field": Rule("str", optional=True),
        "rotate": Rule("bool"),
        "repair": Rule("bool"),
        "n_shapes": Rule("int", minimum=1),
        "n_vertices": Rule("int", minimum=1, optional=True),
        "num_classes": Rule("int", minimum=1),
        "test_fraction": Rule("number", minimum=0, below=1, optional=True),
        "class_names": Rule("str_list", optional=True),
        "label_kind": Rule("str", choices=("auto", "vertex", "face")),
        "test": Rule("names", optional=True),
        "train_indices": Rule("indices"),
        "test_indices": Rule("indices"),
        "val_indices": Rule("indices", optional=True),
        "target_exponent": Rule("number"),
        "workers": Rule("int", minimum=0, optional=True),
    }

    kind: str = _rule("synthetic", "str", choices=DATASET_KINDS)
    seed: int = _rule(0, "int", minimum=0)  # seeds the validation split
    val_fraction: float | None = _rule(None, "number", minimum=0, below=1, optional=True)
    val_count: int | None = _rule(None, "int", minimum=0, optional=True)  # overrides val_fraction
    # A shape that fails to load or preprocess: stop before training, listing every failure (raise), or
    # train without it (skip; the run lists it in train.log and metrics.json).
    on_error: str = _rule("raise", "str", choices=ON_ERROR_CHOICES)
    # Where the prepared patch operators of the training and validation shapes live between steps:
    # device, host (copied ahead of each step), stream (read for every step) or auto (by size and free
    # memory); see zernet.training.residency. Every level trains the same numbers.
    residency: str = _rule("auto", "str", choices=RESIDENCY_LEVELS)
    options: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if isinstance(self.options, Mapping) and "strict" in self.options:
            options = dict(self.options)
            strict = options.pop("strict")
            Rule("bool").check("data.strict", strict)
            warnings.warn(
                f"data.strict is deprecated: use data.on_error: {'raise' if strict else 'skip'} "
                "(strict: true is on_error: raise, strict: false is on_error: skip)",
                FutureWarning,
                stacklevel=2,
            )
            object.__setattr__(self, "options", options)
            object.__setattr__(self, "on_error", "raise" if strict else "skip")
        super().__post_init__()
        if "area" in self.options:
            raise ConfigError("data.area is not a data option: the target area is patch.area")
        unknown = sorted(set(self.options) - set(data_option_names(self.kind)))
        if unknown:
            raise ConfigError(
                f"unknown key data.{unknown[0]} for data kind {self.kind!r} (known: "
                f"{', '.join(sorted(set(data_option_names(self.kind)) | set(self._core_names())))})"
            )
        # data.forms: {form: copies per training shape} (zernet.data.training_forms): names, rates and the
        # packages the forms need, checked before any data is loaded.
        try:
            check_form_rates(self.options.get("forms"))
        except DatasetError as error:
            raise ConfigError(f"data.{error}") from None


@dataclass(frozen=True)
class PatchSection(_Section):
    """Area normalisation and the patch settings, one :class:`~zernet.operators.patch.PatchConfig` mapping per scale."""

    NAME: ClassVar[str] = "patch"

    area: float | None = _rule(None, "number", positive=True, optional=True)  # None: the data set's default
    # A fixed factor on every shape's coordinates instead of normalising its area (scans in known units,
    # partial scans); checkpoints keep it and `predict` applies it. Not with `area`.
    scale: float | None = _rule(None, "number", positive=True, optional=True)
    scales: list[dict[str, Any]] = field(default_factory=list)  # []: the data set's default

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.area is not None and self.scale is not None:
            raise ConfigError(
                f"patch.area ({self.area}) and patch.scale ({self.scale}) both set: give one (area normalises "
                "each shape to that area, scale multiplies every shape's coordinates by one factor)"
            )
        if not isinstance(self.scales, (list, tuple)):
            raise ConfigError(
                "patch.scales must be a list of patch settings, one per scale (e.g. [{r0: 5.5}]), "
                f"or [] for the data set's default, got {self.scales!r}"
            )
        object.__setattr__(self, "scales", [copy.deepcopy(scale) for scale in self.scales])
        known = {f.name for f in dataclasses.fields(PatchConfig)}
        for i, scale in enumerate(self.scales):
            if not isinstance(scale, dict):
                raise ConfigError(f"patch.scales.{i} must be a mapping of PatchConfig fields, got {scale!r}")
            extra = set(scale) - known
            if extra:
                raise ConfigError(
                    f"unknown key patch.scales.{i}.{sorted(extra)[0]} (known: {', '.join(sorted(known))})"
                )
            if "r0" not in scale:
                raise ConfigError(f"patch.scales.{i}.r0 (the patch radius) is required")
            try:
                PatchConfig(**scale)
            except (TypeError, ValueError) as error:
                raise ConfigError(f"patch.scales.{i}: {error}") from None

    def patch_configs(self) -> list[PatchConfig]:
        """One :class:`~zernet.operators.patch.PatchConfig` per scale."""
        return [PatchConfig(**scale) for scale in self.scales]

    def size(self) -> float | FixedScale | None:
        """What every shape is scaled to: ``area``, a :class:`~zernet.geometry.FixedScale` of ``scale``, or
        None (the data set's default area)."""
        return FixedScale(float(self.scale)) if self.scale is not None else self.area


@dataclass(frozen=True)
class ModelSection(_Section):
    """The model's registry name; ``options`` go to its constructor (``widths``, ``dropout``, ...)."""

    NAME: ClassVar[str] = "model"
    OPTION_RULES: ClassVar[dict[str, Rule]] = {
        "widths": Rule("int_list"),
        "dropout": Rule("number", minimum=0, below=1),
        "angular_resolution": Rule("int", minimum=1),
        "pooling": Rule("str"),
        "n_max": Rule("int", minimum=0),
        "k": Rule("int", minimum=1),
    }

    name: str = "zernet"
    options: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        super().__post_init__()
        models = available_models()
        if self.name not in models:
            # Checked here, before any preprocessing, so a typo fails in a second rather than after minutes.
            raise ConfigError(f"model.name must be one of {', '.join(models)}, got {self.name!r}")


@dataclass(frozen=True)
class TrainSection(_Section):
    """Optimisation, early stopping, device and precision."""

    NAME: ClassVar[str] = "train"

    epochs: int = _rule(200, "int", minimum=0)
    lr: float = _rule(1.0e-3, "number", positive=True)
    lr_schedule: str = _rule("constant", "str", choices=LR_SCHEDULES)  # cosine: from lr to 0 over epochs
    # Epochs the cosine spans (null: train.epochs). Set it when a run is trained in pieces with a growing
    # epoch budget (resume), so the schedule stays that of the whole run.
    lr_schedule_epochs: int | None = _rule(None, "int", minimum=1, optional=True)
    weight_decay: float = _rule(0.0, "number")
    loss: str = _rule("auto", "str", choices=LOSSES)  # auto: cross_entropy / mse by task
    # Correspondence by template vertex only: the cross-entropy's target spread over the template vertices
    # within this fraction of the template's geodesic diameter (a Gaussian of the distance, σ = radius / 2;
    # zernet.inference.template_graph), so a near miss costs less than a far one. 0: the hard label.
    label_radius: float = _rule(0.0, "number", minimum=0, below=1)
    standardize_targets: bool = _rule(True, "bool")  # regression: train on (y - mean) / std
    target_transform: str = _rule("none", "str", choices=TARGET_TRANSFORMS)  # log: the loss sees relative errors
    standardize_features: bool = _rule(False, "bool")  # (x - mean) / std per input channel
    patience: int | None = _rule(20, "int", minimum=1, optional=True)  # epochs without a better val metric
    seed: int = _rule(0, "int", minimum=0)
    shapes_per_step: int = _rule(1, "int", minimum=1)  # surfaces concatenated into one optimiser step
    device: str = _rule("auto", "str")  # auto (cuda if available) | cpu | cuda | cuda:1 ...
    threads: int | None = _rule(None, "int", minimum=1, optional=True)  # torch CPU threads
    grad_clip: float | None = _rule(None, "number", positive=True, optional=True)
    # bfloat16: linear layers under torch.autocast (convolutions stay float32); ~3x faster matmuls on CPUs
    # with AVX-512 BF16 or AMX and on recent GPUs, slower on CPUs without them.
    precision: str = _rule("float32", "str", choices=PRECISIONS)
    # Random rigid rotation (about the up axis y, or any) and scaling by [1 - a, 1 + a] of the xyz/normals
    # inputs of every training shape (zernet.training.augment); meaningless for rotation-invariant features.
    augment_rotation: str = _rule("none", "str", choices=AUGMENT_ROTATIONS)
    augment_scale: float = _rule(0.0, "number", minimum=0, below=1)
    # Other people's proportions, on the xyz inputs: each axis scaled by its own factor in [1 - a, 1 + a]
    # (anisotropy), and a smooth random displacement of amplitude ``warp`` times the shape's RMS radius.
    augment_anisotropy: float = _rule(0.0, "number", minimum=0, below=1)
    augment_warp: float = _rule(0.0, "number", minimum=0, below=1)
    # Also keep every epoch's weights as epochs/epoch_XXX.pt (no optimiser state): learning curves on any
    # split afterwards (zernet evaluate RUN/epochs/epoch_003.pt); the model is still chosen on validation.
    keep_epochs: bool = _rule(False, "bool")
    # Where the weights start (zernet.training.init_from): null (fresh), a run folder or checkpoint file, or
    # "pretrained:NAME" for weights shipped with zernet (zernet/pretrained/); `zernet train --init-from`
    # overrides it. A resumed run continues from its own weights whatever this says.
    init_from: str | None = _rule(None, "str", optional=True)


@dataclass(frozen=True)
class EvalSection(_Section):
    """Pictures written after training."""

    NAME: ClassVar[str] = "eval"

    renders: int = _rule(3, "int", minimum=0)  # test shapes rendered (prediction, truth, error)
    plots: bool = _rule(True, "bool")  # write plots at all
    # Correspondence: the predicted probabilities refined by the agreement of this many rings of mesh
    # neighbours (zernet.inference.refine); segmentation: averaged over the shape's rings, at the vertices the
    # network is unsure of.
    # A number, or candidates of which the best on the validation split is used.
    refine_rings: list[int] = _rule((0,), "int_list")
    # Correspondence: how many times the refinement by rings is repeated, each pass refining the last one's
    # scores, so agreement travels beyond one ring radius. Candidates are chosen with the rings on validation.
    refine_passes: list[int] = _rule((1,), "int_list")
    # Correspondence, after the rings: the global refinement (zernet.inference.spectral_refine), the prediction
    # kept within this radius (a fraction of the template's geodesic diameter) of a spectral map read from it;
    # 0 turns it off. A number, or candidates of which the best on the validation split (after the rings) is used.
    refine_spectral: list[float] = _rule((0.0,), "number_list")

    def __post_init__(self) -> None:
        if _is_int(self.refine_rings):
            object.__setattr__(self, "refine_rings", [self.refine_rings])
        if _is_int(self.refine_passes):
            object.__setattr__(self, "refine_passes", [self.refine_passes])
        if _is_number(self.refine_spectral):
            object.__setattr__(self, "refine_spectral", [self.refine_spectral])
        super().__post_init__()
        object.__setattr__(self, "refine_rings", list(self.refine_rings))  # a plain list in YAML and JSON
        object.__setattr__(self, "refine_passes", list(self.refine_passes))
        object.__setattr__(self, "refine_spectral", [float(v) for v in self.refine_spectral])
        if not self.refine_rings or min(self.refine_rings) < 0:
            raise ConfigError(
                f"eval.refine_rings must be a non-empty list of integers >= 0, got {list(self.refine_rings)!r}"
            )
        if not self.refine_passes or min(self.refine_passes) < 1:
            raise ConfigError(
                f"eval.refine_passes must be a non-empty list of integers >= 1, got {list(self.refine_passes)!r}"
            )
        if not self.refine_spectral or not all(0 <= v <= 1 for v in self.refine_spectral):
            raise ConfigError(
                "eval.refine_spectral must be a non-empty list of numbers in [0, 1] (radii as fractions of the "
                f"template's geodesic diameter; 0: off), got {list(self.refine_spectral)!r}"
            )


_SECTIONS = {
    "data": DataSection,
    "patch": PatchSection,
    "model": ModelSection,
    "train": TrainSection,
    "eval": EvalSection,
}
_DEFAULT_CACHE_DIR = ".zernet-cache"


@dataclass(frozen=True)
class RunConfig:
    """A complete, checked run configuration."""

    data: DataSection = field(default_factory=DataSection)
    patch: PatchSection = field(default_factory=PatchSection)
    model: ModelSection = field(default_factory=ModelSection)
    train: TrainSection = field(default_factory=TrainSection)
    eval: EvalSection = field(default_factory=EvalSection)
    cache_dir: str | None = _DEFAULT_CACHE_DIR  # preprocessed patch operators, reused across runs

    def __post_init__(self) -> None:
        for name, section_type in _SECTIONS.items():
            if not isinstance(getattr(self, name), section_type):
                raise ConfigError(f"RunConfig.{name} must be a {section_type.__name__}")
        Rule("path", optional=True).check("cache_dir", self.cache_dir)

    @classmethod
    def from_dict(cls, config: Mapping[str, Any]) -> RunConfig:
        """Check ``config`` (sections as mappings) and fill in the defaults; a missing or null section or
        ``cache_dir`` takes its default."""
        if not isinstance(config, Mapping):
            raise ConfigError(f"config must be a mapping of sections, got {type(config).__name__}")
        known = list(_SECTIONS) + ["cache_dir"]
        unknown = set(config) - set(known)
        if unknown:
            raise ConfigError(f"unknown config section {sorted(unknown)[0]!r} (known: {', '.join(sorted(known))})")
        sections = {
            name: section_type.from_dict({} if config.get(name) is None else config[name])
            for name, section_type in _SECTIONS.items()
        }
        cache_dir = config.get("cache_dir")
        return cls(**sections, cache_dir=_DEFAULT_CACHE_DIR if cache_dir is None else cache_dir)

    def to_dict(self) -> dict[str, Any]:
        """The plain mapping written to ``config.yaml`` and into checkpoints (the inverse of from_dict)."""
        out: dict[str, Any] = {name: getattr(self, name).to_dict() for name in _SECTIONS}
        out["cache_dir"] = self.cache_dir
        return out


#: Every key the loop itself understands, with its default, as a plain mapping.
DEFAULT_CONFIG: dict[str, Any] = RunConfig().to_dict()


def parse_config(config: Mapping[str, Any] | RunConfig) -> RunConfig:
    """A :class:`RunConfig` from a mapping (a YAML file's contents, a stored ``config.yaml``), checked."""
    if isinstance(config, RunConfig):
        return config
    return RunConfig.from_dict(config)


def resolve_config(config: Mapping[str, Any] | RunConfig) -> dict:
    """Check ``config`` and return it as a plain mapping with every default filled in."""
    return parse_config(config).to_dict()


# --------------------------------------------------------------------------------------------------------
# YAML files and overrides
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
    """Read a YAML configuration file into a plain mapping (checked and completed by :func:`parse_config`)."""
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


def read_config(path: str | Path, overrides: Sequence[str] = ()) -> RunConfig:
    """A YAML file with ``key=value`` overrides applied, checked: what ``zernet train CONFIG --set ...`` runs."""
    return parse_config(apply_overrides(load_config(path), overrides))
