r"""ZerNet models and the model registry.

Every model has the signature ``model(x (N, C_in), geometry: Geometry) -> (N, C_out)`` and is built by
:func:`build_model` from a registered name. This module registers ``"zernet"`` (single scale) and
``"zernet-multiscale"``; :mod:`zernet.nn.directional` registers ``"zernet-directional"`` and
:mod:`zernet.nn.baselines` registers ``"feastnet"`` and ``"paper-zernet"`` with :func:`register_model`
(they import this module, never the reverse: :func:`build_model` imports them lazily when asked for a name
it does not know yet).

Widths follow the paper (section 4): the convolution widths, then the hidden linear width.

=============== ======================== =============================================
task            ``widths``               network
=============== ======================== =============================================
correspondence  ``(64, 128, 256, 512)``  Conv64 -> Conv128 -> Conv256 -> Lin512 -> Lin(C)
segmentation    ``(32, 64, 128, 256)``   Conv32 -> Conv64 -> Conv128 -> Lin256 -> Lin8
regression      ``(128, 256, 512, 800)`` Conv128 -> Conv256 -> Conv512 -> Lin800 -> Lin1
=============== ======================== =============================================
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Sequence

import torch
from torch import Tensor, nn

from .conv import ZernikeConv
from .geometry import Geometry

__all__ = [
    "MODEL_REGISTRY",
    "TASK_WIDTHS",
    "register_model",
    "available_models",
    "build_model",
    "ZernikeBlock",
    "ZerNet",
    "MultiScaleZerNet",
]

MODEL_REGISTRY: dict[str, Callable[..., nn.Module]] = {}

TASK_WIDTHS = {
    "correspondence": (64, 128, 256, 512),
    "segmentation": (32, 64, 128, 256),
    "regression": (128, 256, 512, 800),
}

# Modules that register further models; imported on demand by build_model (they import this module).
_PLUGIN_MODULES = ("zernet.nn.directional", "zernet.nn.baselines")


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


def _load_plugins() -> None:
    for module in _PLUGIN_MODULES:
        try:
            importlib.import_module(module)
        except ImportError:
            continue


def available_models() -> list[str]:
    """Registered model names (after importing the optional model modules)."""
    _load_plugins()
    return sorted(MODEL_REGISTRY)


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
    if name not in MODEL_REGISTRY:
        _load_plugins()
    if name not in MODEL_REGISTRY:
        raise ValueError(f"unknown model {name!r}; available: {', '.join(sorted(MODEL_REGISTRY))}")
    return MODEL_REGISTRY[name](in_channels, out_channels, **options)


def _resolve_widths(widths, task) -> tuple[int, ...]:
    if widths is None:
        task = task or "correspondence"
        if task not in TASK_WIDTHS:
            raise ValueError(f"unknown task {task!r} for default widths; one of {sorted(TASK_WIDTHS)}")
        widths = TASK_WIDTHS[task]
    widths = tuple(int(w) for w in widths)
    if len(widths) < 2 or min(widths) < 1:
        raise ValueError(
            f"widths must list at least one convolution width and the hidden linear width, all >= 1, "
            f"e.g. (64, 128, 256, 512); got {widths}"
        )
    return widths


def _activation(name: str) -> nn.Module:
    if name == "relu":
        return nn.ReLU()
    if name == "elu":
        return nn.ELU()
    raise ValueError(f"activation must be 'relu' or 'elu', got {name!r}")


def _norm(name: str | None, width: int) -> nn.Module:
    if name is None or name == "none":
        return nn.Identity()
    if name == "batch":
        return nn.BatchNorm1d(width)
    if name == "layer":
        return nn.LayerNorm(width)
    raise ValueError(f"norm must be None, 'batch' or 'layer', got {name!r}")


def _split(width: int, parts: int) -> list[int]:
    base, extra = divmod(width, parts)
    return [base + (1 if i < extra else 0) for i in range(parts)]


class ZernikeBlock(nn.Module):
    r"""One convolution block: Zernike convolutions at one or several scales, concatenated, then norm and
    activation.

    .. math::
        \mathbf{y} = \sigma\Big(\operatorname{norm}\big(\big\Vert_{i} \operatorname{ZernikeConv}_i(\mathbf{x},
            \text{operators}[\text{scales}_i])\big)\Big)

    Args:
        in_channels: ``C_in``.
        out_channels: ``C_out``, split as evenly as possible over the scales (``64`` over three scales:
            ``22 + 21 + 21``).
        scales: operator index of each branch, e.g. ``(0,)`` or ``(0, 1, 2)``.
        activation, norm: see :class:`ZerNet`.
        **conv_options: ``n_max``, ``angular_resolution``, ``pooling``, ``bias`` of :class:`ZernikeConv`.

    Shapes: ``x`` ``(N, C_in)``, ``operators`` a list of operators -> ``(N, C_out)``.
    """

    def __init__(self, in_channels, out_channels, scales=(0,), activation="relu", norm=None, **conv_options):
        super().__init__()
        if conv_options.get("pooling", "max") == "none":
            raise ValueError("model convolution blocks need a pooled output; pooling='none' is for single layers")
        self.scales = tuple(int(s) for s in scales)
        widths = _split(out_channels, len(self.scales))
        if min(widths) < 1:
            raise ValueError(f"width {out_channels} cannot be split over {len(self.scales)} scales")
        self.convs = nn.ModuleList(ZernikeConv(in_channels, w, **conv_options) for w in widths)
        self.norm = _norm(norm, out_channels)
        self.act = _activation(activation)

    def forward(self, x: Tensor, operators: Sequence) -> Tensor:
        if max(self.scales) >= len(operators):
            raise ValueError(f"block uses operator scales {self.scales} but the geometry has {len(operators)}")
        outs = [conv(x, operators[s]) for conv, s in zip(self.convs, self.scales)]
        y = outs[0] if len(outs) == 1 else torch.cat(outs, dim=1)
        return self.act(self.norm(y))


class _ZerNetBase(nn.Module):
    def _build_input(self, input_width, activation) -> int:
        """The optional per-vertex linear layer before the first convolution; returns its width."""
        input_width = int(input_width or 0)
        if input_width < 0:
            raise ValueError(f"input_width must be >= 0 (0 or None: no input layer), got {input_width}")
        self.input = nn.Linear(self.in_channels, input_width) if input_width else None
        self.input_act = _activation(activation) if input_width else None
        return input_width or self.in_channels

    def _build_head(self, channels, hidden, out_channels, activation, dropout):
        self.hidden = nn.Linear(channels, hidden)
        self.hidden_act = _activation(activation)
        self.dropout = nn.Dropout(dropout)
        self.output = nn.Linear(hidden, out_channels)

    def reset_parameters(self) -> None:
        for module in self.modules():
            if module is not self and hasattr(module, "reset_parameters"):
                module.reset_parameters()

    def forward(self, x: Tensor, geometry: Geometry) -> Tensor:
        """``x`` ``(N, C_in)``, ``geometry.operators`` -> ``(N, C_out)``."""
        if x.dim() != 2 or x.shape[1] != self.in_channels:
            raise ValueError(f"{self.__class__.__name__} expects x of shape (N, {self.in_channels}), got {tuple(x.shape)}")
        inputs = x
        if self.input is not None:
            x = self.input_act(self.input(x))
        for block in self.blocks:
            x = block(x, geometry.operators)
        if self.input_skip:
            x = torch.cat([x, inputs], dim=1)
        x = self.hidden_act(self.hidden(x))
        return self.output(self.dropout(x))


@register_model("zernet")
class ZerNet(_ZerNetBase):
    r"""Single-scale ZerNet (paper section 4.1): ``[Lin(input_width), σ] -> (ZernikeConv(w_i), [norm], σ)_i
    -> Lin(widths[-1]), σ -> Dropout -> Lin(out_channels)``.

    Args:
        in_channels: ``C_in`` (3 for xyz).
        out_channels: ``C_out`` (classes, or 1 for regression).
        widths: convolution widths then the hidden linear width; default from ``task``.
        task: ``"correspondence"`` (default), ``"segmentation"`` or ``"regression"``: picks the paper's
            widths (module docstring) when ``widths`` is not given.
        n_max: Zernike degree of the convolutions (5: k = 21, the paper's).
        angular_resolution: ``s`` kernel rotations (paper: 1 to 16; the harmonic form makes 16 cheap).
        pooling: angular pooling of every convolution: ``"max"`` (paper), ``"continuous"``, ``"mean"``.
        activation: ``"relu"`` (default) or ``"elu"``, after every convolution and the hidden linear.
        dropout: probability before the output layer (0.25, the authors' release).
        norm: ``None`` (paper), ``"batch"`` or ``"layer"`` after every convolution.
        input_width: width of a per-vertex linear layer (and activation) before the first convolution, which
            mixes many descriptive input channels (``features: shape``) into a few before they are convolved,
            as FeaStNet does (``0`` or ``None``: the first convolution takes the raw inputs, the paper's model).
        input_skip: also feed the input features to the hidden linear layer (concatenated to the last
            block's output), so descriptive per-vertex inputs such as ``features: shape`` reach the head
            unchanged and the convolutions only add context.
        scale: which of ``geometry.operators`` the convolutions use (0).

    Shapes: ``x`` ``(N, C_in)``, ``geometry.operators[scale]`` -> ``(N, C_out)`` unnormalised scores.
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        widths: Sequence[int] | None = None,
        task: str | None = None,
        n_max: int = 5,
        angular_resolution: int = 16,
        pooling: str = "max",
        activation: str = "relu",
        dropout: float = 0.25,
        norm: str | None = None,
        input_width: int | None = None,
        input_skip: bool = False,
        scale: int = 0,
    ):
        super().__init__()
        self.in_channels, self.out_channels = int(in_channels), int(out_channels)
        self.widths = _resolve_widths(widths, task)
        conv = dict(n_max=n_max, angular_resolution=angular_resolution, pooling=pooling)
        self.blocks = nn.ModuleList()
        channels = self._build_input(input_width, activation)
        for w in self.widths[:-1]:
            self.blocks.append(ZernikeBlock(channels, w, scales=(scale,), activation=activation, norm=norm, **conv))
            channels = w
        self.input_skip = bool(input_skip)
        self._build_head(channels + (self.in_channels if self.input_skip else 0), self.widths[-1],
                         self.out_channels, activation, dropout)


@register_model("zernet-multiscale")
class MultiScaleZerNet(_ZerNetBase):
    r"""Multi-scale ZerNet (paper section 4.1: radii 4.5, 5.5, 6.75 at area 15000 with 18000, 12000 and
    8000 samples, in ``geometry.operators[0..2]``).

    The paper gives no wiring. Here every convolution block looks at all scales in parallel
    (``wiring="parallel"``, default): block ``i`` has one :class:`ZernikeConv` per scale with a third of the
    block's width each, concatenated (Inception-style), so every layer mixes fine and coarse context and the
    cost is one single-scale block's contraction plus two more sparse decompositions; widths match the
    single-scale model, so the two compare at equal feature sizes. ``wiring="sequential"`` instead uses
    scale ``i`` for block ``i`` (receptive field growing with depth, the cheapest option).

    Args:
        in_channels, out_channels, widths, task, n_max, angular_resolution, pooling, activation, dropout,
        norm, input_width, input_skip: as :class:`ZerNet`.
        n_scales: number of operators used (3).
        wiring: ``"parallel"`` or ``"sequential"``.

    Shapes: ``x`` ``(N, C_in)``, ``geometry.operators[0..n_scales-1]`` -> ``(N, C_out)``.
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        widths: Sequence[int] | None = None,
        task: str | None = None,
        n_max: int = 5,
        angular_resolution: int = 16,
        pooling: str = "max",
        activation: str = "relu",
        dropout: float = 0.25,
        norm: str | None = None,
        input_width: int | None = None,
        input_skip: bool = False,
        n_scales: int = 3,
        wiring: str = "parallel",
    ):
        super().__init__()
        if wiring not in ("parallel", "sequential"):
            raise ValueError(f"wiring must be 'parallel' or 'sequential', got {wiring!r}")
        self.in_channels, self.out_channels = int(in_channels), int(out_channels)
        self.widths = _resolve_widths(widths, task)
        self.n_scales, self.wiring = int(n_scales), wiring
        conv = dict(n_max=n_max, angular_resolution=angular_resolution, pooling=pooling)
        self.blocks = nn.ModuleList()
        channels = self._build_input(input_width, activation)
        for i, w in enumerate(self.widths[:-1]):
            scales = tuple(range(self.n_scales)) if wiring == "parallel" else (min(i, self.n_scales - 1),)
            self.blocks.append(ZernikeBlock(channels, w, scales=scales, activation=activation, norm=norm, **conv))
            channels = w
        self.input_skip = bool(input_skip)
        self._build_head(channels + (self.in_channels if self.input_skip else 0), self.widths[-1],
                         self.out_channels, activation, dropout)
