"""What every model shares: the model signature, the default widths per task, and the ZerNet skeleton.

Every model has the signature ``model(x (N, C_in), geometry: Geometry) -> (N, C_out)`` and says which
per-surface operators it needs beyond the patch operators: ``directional_order`` is ``None`` for models
without directional layers, else the Fourier order ``L`` of the
:class:`~zernet.operators.DirectionalOperator` it reads from ``geometry.directional`` (the data pipeline
builds them with ``geometry.with_directional(L)``).

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

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from zernet.operators import Geometry

__all__ = [
    "TASK_WIDTHS",
    "resolve_widths",
    "activation_module",
    "norm_module",
    "split_width",
    "SurfaceModel",
    "ZerNetBase",
]

TASK_WIDTHS = {
    "correspondence": (64, 128, 256, 512),
    "segmentation": (32, 64, 128, 256),
    "regression": (128, 256, 512, 800),
}


def resolve_widths(widths: Sequence[int] | None, task: str | None) -> tuple[int, ...]:
    """``widths`` checked (at least one convolution width and the hidden width, all >= 1), or the
    task's default from :data:`TASK_WIDTHS` when ``None`` (``task`` ``None``: correspondence)."""
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


def activation_module(name: str) -> nn.Module:
    """``"relu"`` or ``"elu"`` as a module."""
    if name == "relu":
        return nn.ReLU()
    if name == "elu":
        return nn.ELU()
    raise ValueError(f"activation must be 'relu' or 'elu', got {name!r}")


def norm_module(name: str | None, width: int) -> nn.Module:
    """``None``/``"none"`` (identity), ``"batch"`` or ``"layer"`` normalisation of ``width`` channels."""
    if name is None or name == "none":
        return nn.Identity()
    if name == "batch":
        return nn.BatchNorm1d(width)
    if name == "layer":
        return nn.LayerNorm(width)
    raise ValueError(f"norm must be None, 'batch' or 'layer', got {name!r}")


def split_width(width: int, parts: int) -> list[int]:
    """``width`` split into ``parts`` as evenly as possible, larger parts first (64 over 3: 22, 21, 21)."""
    base, extra = divmod(width, parts)
    return [base + (1 if i < extra else 0) for i in range(parts)]


class SurfaceModel(nn.Module):
    """Root of zernet's models: ``forward(x (N, C_in), geometry) -> (N, C_out)``.

    Attributes:
        directional_order: Fourier order of the directional operators the model reads from
            ``geometry.directional``, or ``None`` (class default) when it needs none.
    """

    directional_order: int | None = None

    @classmethod
    def directional_order_for(cls, **options) -> int | None:
        """The ``directional_order`` a model built with these constructor options will have (``None``
        here), so the data can be prepared before the model is built."""
        return None

    def reset_parameters(self) -> None:
        """Re-initialise every sub-module that has parameters of its own."""
        for module in self.modules():
            if module is not self and hasattr(module, "reset_parameters"):
                module.reset_parameters()

    def check_features(self, x: Tensor) -> None:
        """``ValueError`` unless ``x`` is ``(N, in_channels)``."""
        if x.dim() != 2 or x.shape[1] != self.in_channels:
            raise ValueError(
                f"{self.__class__.__name__} expects x of shape (N, {self.in_channels}), got {tuple(x.shape)}"
            )


class ZerNetBase(SurfaceModel):
    r"""``[Lin(input_width), σ] -> (block_i, σ)_i -> Lin(widths[-1]), σ -> Dropout -> Lin(out_channels)``.

    The constructor arguments every ZerNet family shares. A family only says how block ``i`` is built, by
    overriding :meth:`init_block`, which receives the family's own constructor options (e.g. ``scale``,
    ``n_scales``, ``wiring``, ``ridge``); modules are created in the order input layer, blocks, head.

    Args:
        in_channels: ``C_in`` (3 for xyz).
        out_channels: ``C_out`` (classes, or 1 for regression).
        widths: convolution widths then the hidden linear width; default from ``task``.
        task: ``"correspondence"`` (default), ``"segmentation"`` or ``"regression"``: picks the paper's
            widths (:data:`TASK_WIDTHS`) when ``widths`` is not given.
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
        **block_options: the family's own options, passed to :meth:`init_block`.

    Shapes: ``x`` ``(N, C_in)``, ``geometry.operators`` -> ``(N, C_out)`` unnormalised scores.
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
        **block_options,
    ):
        super().__init__()
        self.in_channels, self.out_channels = int(in_channels), int(out_channels)
        self.widths = resolve_widths(widths, task)
        self.conv_options = dict(n_max=n_max, angular_resolution=angular_resolution, pooling=pooling)
        self.activation, self.norm_name = activation, norm
        self.blocks = nn.ModuleList()
        channels = self._build_input(input_width, activation)
        for index, width in enumerate(self.widths[:-1]):
            self.blocks.append(self.init_block(index, channels, width, **block_options))
            channels = width
        self.input_skip = bool(input_skip)
        self._build_head(channels + (self.in_channels if self.input_skip else 0), self.widths[-1], dropout)

    def init_block(self, index: int, in_channels: int, out_channels: int, **block_options) -> nn.Module:
        """Convolution block ``index``: ``block(x (N, in_channels), geometry.operators) -> (N, out_channels)``
        with its activation applied. Families override it; ``self.conv_options`` (``n_max``,
        ``angular_resolution``, ``pooling``), ``self.activation`` and ``self.norm_name`` are set."""
        raise NotImplementedError(f"{type(self).__name__} must define init_block")

    def _build_input(self, input_width, activation) -> int:
        """The optional per-vertex linear layer before the first convolution; returns its width."""
        input_width = int(input_width or 0)
        if input_width < 0:
            raise ValueError(f"input_width must be >= 0 (0 or None: no input layer), got {input_width}")
        self.input = nn.Linear(self.in_channels, input_width) if input_width else None
        self.input_act = activation_module(activation) if input_width else None
        return input_width or self.in_channels

    def _build_head(self, channels: int, hidden: int, dropout: float) -> None:
        self.hidden = nn.Linear(channels, hidden)
        self.hidden_act = activation_module(self.activation)
        self.dropout = nn.Dropout(dropout)
        self.output = nn.Linear(hidden, self.out_channels)

    def forward(self, x: Tensor, geometry: Geometry) -> Tensor:
        """``x`` ``(N, C_in)``, ``geometry.operators`` -> ``(N, C_out)``."""
        self.check_features(x)
        inputs = x
        if self.input is not None:
            x = self.input_act(self.input(x))
        for block in self.blocks:
            x = block(x, geometry.operators)
        if self.input_skip:
            x = torch.cat([x, inputs], dim=1)
        x = self.hidden_act(self.hidden(x))
        return self.output(self.dropout(x))
