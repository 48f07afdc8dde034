"""The descriptor model: a zernet network with per-vertex descriptors as output, and its file format.

:class:`MatchingSpec` says everything the matcher needs besides the weights: the network (a registered
zernet model, :mod:`zernet.nn.models`, with ``out_channels`` = the descriptor size and no dropout), its
inputs (feature kind, patch settings, area, the input standardisation measured on the training shapes)
and the spectral settings (eigenpairs of the functional-map layer, its regularisation, ZoomOut's range).

A descriptor model file is a model file of kind ``descriptors`` (:mod:`zernet.inference.model_file`):
``{"spec": MatchingSpec.to_dict(), "model": state dict, "provenance": {...}}`` beside the format fields.
The model shipped with zernet is :data:`PRETRAINED_MODEL`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from zernet.inference.model_file import model_file, pretrained_path, read_model_file
from zernet.io_utils import atomic_save_torch, plain
from zernet.nn.models import build_model
from zernet.operators import PatchConfig

__all__ = [
    "PRETRAINED_MODEL",
    "MatchingSpec",
    "DescriptorModel",
    "save_matching_model",
    "load_matching_model",
]

#: The descriptor model shipped in the package (trained on generated bodies only; provenance beside it).
PRETRAINED_MODEL = pretrained_path("bodies-match-descriptors")


@dataclass(frozen=True)
class MatchingSpec:
    """What the matcher needs besides the weights (module docstring).

    Attributes:
        feature_kind: zernet feature parts joined by "+", optionally with ``hks``
            (:func:`zernet.matching.shapes.input_features`).
        in_channels: input channels of that kind.
        descriptor_size: per-vertex descriptor channels (the network's output).
        patch_configs: patch settings, one dict per scale (:class:`zernet.operators.PatchConfig` fields).
        area: the area every surface is scaled to.
        model_name: a registered model (:func:`zernet.nn.models.build_model`).
        model_options: its constructor options.
        n_fmap: eigenpairs of the functional-map layer.
        regularisation, gamma: of the layer (:func:`zernet.matching.fmap.functional_map`).
        zoomout_end, zoomout_step: ZoomOut from ``n_fmap`` to ``zoomout_end`` eigenpairs (0: no ZoomOut).
        zoomout_descriptor_weight: weight of the descriptors (scaled to unit typical length) appended to the
            spectral embeddings in ZoomOut's nearest-neighbour searches (0: plain ZoomOut).
        descriptor_vertices: the model reads a larger surface through a coarse copy of about this many
            vertices (:func:`zernet.matching.shapes.prepare_shape`; None: the surface itself).
        align_target: turn the target's pose-dependent inputs (xyz, normals) into the source's frame before
            its descriptors are computed, trying the 4 proper sign choices of the principal axes and keeping
            the most consistent match (:func:`zernet.matching.match.candidate_alignments`).
        feature_mean, feature_std: per-channel standardisation of the inputs (training shapes' statistics).
    """

    feature_kind: str
    in_channels: int
    descriptor_size: int
    patch_configs: tuple[dict, ...]
    area: float
    model_name: str = "zernet"
    model_options: dict = field(default_factory=dict)
    n_fmap: int = 30
    regularisation: float = 1e-3
    gamma: float = 0.5
    zoomout_end: int = 80
    zoomout_step: int = 2
    zoomout_descriptor_weight: float = 0.0
    descriptor_vertices: int | None = None
    align_target: bool = False
    feature_mean: tuple[float, ...] | None = None
    feature_std: tuple[float, ...] | None = None

    @property
    def n_eigen(self) -> int:
        """Eigenpairs a shape needs: the most any step uses."""
        return max(self.n_fmap, self.zoomout_end)

    def patch_config_objects(self) -> list[PatchConfig]:
        return [PatchConfig(**config) for config in self.patch_configs]

    def to_dict(self) -> dict:
        return plain(dataclasses.asdict(self))

    @classmethod
    def from_dict(cls, values: dict) -> MatchingSpec:
        values = dict(values)
        values["patch_configs"] = tuple(dict(c) for c in values["patch_configs"])
        for key in ("feature_mean", "feature_std"):
            if values.get(key) is not None:
                values[key] = tuple(float(v) for v in values[key])
        return cls(**values)


class DescriptorModel(torch.nn.Module):
    """``descriptors = model(features (N, C_in), geometry) -> (N, descriptor_size)``: the spec's network
    applied to standardised inputs."""

    def __init__(self, spec: MatchingSpec):
        super().__init__()
        self.spec = spec
        self.network = build_model(spec.model_name, spec.in_channels, spec.descriptor_size, **spec.model_options)
        mean = np.zeros(spec.in_channels) if spec.feature_mean is None else np.asarray(spec.feature_mean)
        std = np.ones(spec.in_channels) if spec.feature_std is None else np.asarray(spec.feature_std)
        self.register_buffer("feature_mean", torch.as_tensor(mean, dtype=torch.float32))
        self.register_buffer("feature_std", torch.as_tensor(std, dtype=torch.float32))

    def forward(self, features: torch.Tensor, geometry) -> torch.Tensor:
        return self.network((features - self.feature_mean) / self.feature_std, geometry)


def save_matching_model(model: DescriptorModel, path: str | Path, provenance: dict | None = None) -> Path:
    """Write ``model`` (spec, weights, ``provenance``) atomically to ``path``."""
    state = {key: value.detach().cpu().clone() for key, value in model.state_dict().items()}
    contents = {"spec": model.spec.to_dict(), "model": state, "provenance": plain(provenance or {})}
    return atomic_save_torch(model_file("descriptors", contents), path)


def load_matching_model(path: str | Path | None = None) -> tuple[DescriptorModel, dict]:
    """(model in eval mode, provenance) from a file written by :func:`save_matching_model`, a training run
    folder holding ``best.pt``, or ``None``: the shipped :data:`PRETRAINED_MODEL`."""
    path = PRETRAINED_MODEL if path is None else Path(path)
    if path.is_dir():
        path = path / "best.pt"
    stored = read_model_file(path, ("descriptors",), "zernet matching model")
    model = DescriptorModel(MatchingSpec.from_dict(stored["spec"]))
    model.load_state_dict(stored["model"])
    return model.eval(), dict(stored.get("provenance") or {})
