"""The model registry: every model by name, and :func:`build_model`.

The built-in families are imported here and listed in :data:`MODEL_REGISTRY`; :func:`register_model`
adds a user's own builder under a new name.
"""

from __future__ import annotations

from collections.abc import Callable

from torch import nn

from .baselines import FeaStNet
from .directional import DirectionalZerNet
from .paper import PaperZerNet
from .zernet import MultiScaleZerNet, ZerNet

__all__ = [
    "MODEL_REGISTRY",
    "register_model",
    "available_models",
    "build_model",
    "directional_order",
    "reads_patch_operators",
]

MODEL_REGISTRY: dict[str, Callable[..., nn.Module]] = {
    "zernet": ZerNet,
    "zernet-multiscale": MultiScaleZerNet,
    "zernet-directional": DirectionalZerNet,
    "feastnet": FeaStNet,
    "paper-zernet": PaperZerNet,
}


def register_model(name: str):
    """Decorator registering ``builder(in_channels, out_channels, **options) -> nn.Module`` as ``name``."""

    def decorator(builder):
        if name in MODEL_REGISTRY and MODEL_REGISTRY[name] is not builder:
            existing = MODEL_REGISTRY[name]
            same = getattr(existing, "__qualname__", None) == getattr(builder, "__qualname__", None) and getattr(
                existing, "__module__", None
            ) == getattr(builder, "__module__", None)
            if not same:  # re-registration of the same builder (module reload) is fine
                raise ValueError(f"model name {name!r} is already registered by {existing!r}")
        MODEL_REGISTRY[name] = builder
        return builder

    return decorator


def available_models() -> list[str]:
    """Registered model names."""
    return sorted(MODEL_REGISTRY)


def _builder(name: str) -> Callable[..., nn.Module]:
    if name not in MODEL_REGISTRY:
        raise ValueError(f"unknown model {name!r}; available: {', '.join(sorted(MODEL_REGISTRY))}")
    return MODEL_REGISTRY[name]


def build_model(name: str, in_channels: int, out_channels: int, **options) -> nn.Module:
    """Build a registered model.

    Args:
        name: ``"zernet"``, ``"zernet-multiscale"``, ``"zernet-directional"``, ``"feastnet"``,
            ``"paper-zernet"``, or any name registered with :func:`register_model`.
        in_channels: per-vertex input features ``C_in``.
        out_channels: per-vertex outputs ``C_out`` (classes, or 1 for regression).
        **options: passed to the model's constructor (see its docstring).

    Raises:
        ValueError: unknown name (the message lists the known ones).
    """
    return _builder(name)(in_channels, out_channels, **options)


def directional_order(name: str, **options) -> int | None:
    """Fourier order of the directional operators the model ``name`` built with ``options`` reads from
    ``geometry.directional`` (``None``: it needs none), known before the model is built so the data can
    be prepared with ``geometry.with_directional(order)``. Builders without ``directional_order_for``
    need none."""
    order_for = getattr(_builder(name), "directional_order_for", None)
    return None if order_for is None else order_for(**options)


def reads_patch_operators(name: str) -> bool:
    """Whether the model ``name`` reads ``geometry.operators`` (the patch operators). Builders that set
    ``reads_patch_operators = False`` (graph baselines such as FeaStNet, which read only the mesh edges) are
    trained and run on data sets without them, so they never wait for geodesic patches."""
    return bool(getattr(_builder(name), "reads_patch_operators", True))
