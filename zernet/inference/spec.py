"""A model from its specification: the name, channel counts and options a checkpoint stores.

:func:`model_spec` writes the spec of a run's model (the Zernike degree taken from the patch operators);
:func:`build_model_from_spec` rebuilds the model anywhere from it, freshly initialised, ready for the
stored weights.
"""

from __future__ import annotations

import inspect
from collections.abc import Mapping, Sequence
from typing import Any

import torch

from zernet.inference.errors import ConfigError
from zernet.nn.models import MODEL_REGISTRY, available_models, build_model
from zernet.zernike import num_bases

__all__ = ["model_spec", "build_model_from_spec"]


def model_spec(model, in_channels: int, out_channels: int, patch_configs: Sequence) -> dict:
    """Name, channel counts and options of the model (``model``: a run's model section, with ``name`` and
    ``options``); the Zernike degree follows the patch operators.

    A model's ``n_max`` (or ``k``, the number of bases) must match the operators', so unless the config
    sets it explicitly it is taken from the patch settings — changing ``patch.scales.*.n_max`` alone then
    just works instead of failing with a shape mismatch.
    """
    options = dict(model.options)
    degrees = {int(c.n_max) for c in patch_configs}
    if len(degrees) == 1 and "n_max" not in options and "k" not in options:
        available_models()  # registers the plug-in models
        try:
            accepted = inspect.signature(MODEL_REGISTRY[model.name]).parameters
        except (KeyError, TypeError, ValueError):
            accepted = {}
        n_max = degrees.pop()
        if "n_max" in accepted:
            options["n_max"] = n_max
        elif "k" in accepted:
            options["k"] = num_bases(n_max)
    return {"name": model.name, "in_channels": int(in_channels), "out_channels": int(out_channels), "options": options}


def build_model_from_spec(spec: Mapping[str, Any]) -> torch.nn.Module:
    """The model a :func:`model_spec` (e.g. a checkpoint's ``model_spec``) describes, freshly initialised."""
    try:
        return build_model(spec["name"], spec["in_channels"], spec["out_channels"], **spec["options"])
    except TypeError as error:
        raise ConfigError(f"model {spec['name']!r}: {error}") from None
    except KeyError as error:
        raise ConfigError(f"model.name: {error.args[0] if error.args else error}") from None
