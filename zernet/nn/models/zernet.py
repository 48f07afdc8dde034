r"""The ZerNet models: single-scale :class:`ZerNet`, :class:`MultiScaleZerNet`, and their block."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from zernet.nn.conv import ZernikeConv

from .base import ZerNetBase, activation_module, norm_module, split_width

__all__ = ["ZernikeBlock", "ZerNet", "MultiScaleZerNet"]


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
        activation, norm: see :class:`~zernet.nn.models.base.ZerNetBase`.
        conv: the convolution class (:class:`~zernet.nn.conv.ZernikeConv` or a subclass with its
            constructor, e.g. :class:`~zernet.nn.models.paper.PaperZernikeConv`).
        **conv_options: ``n_max``, ``angular_resolution``, ``pooling``, ``bias`` (and the ``conv`` class's
            own options) of the convolutions.

    Shapes: ``x`` ``(N, C_in)``, ``operators`` a list of operators -> ``(N, C_out)``.
    """

    def __init__(
        self, in_channels, out_channels, scales=(0,), activation="relu", norm=None, conv=ZernikeConv, **conv_options
    ):
        super().__init__()
        if conv_options.get("pooling", "max") == "none":
            raise ValueError("model convolution blocks need a pooled output; pooling='none' is for single layers")
        self.scales = tuple(int(s) for s in scales)
        widths = split_width(out_channels, len(self.scales))
        if min(widths) < 1:
            raise ValueError(f"width {out_channels} cannot be split over {len(self.scales)} scales")
        self.convs = nn.ModuleList(conv(in_channels, w, **conv_options) for w in widths)
        self.norm = norm_module(norm, out_channels)
        self.act = activation_module(activation)

    def forward(self, x: Tensor, operators: Sequence) -> Tensor:
        if max(self.scales) >= len(operators):
            raise ValueError(f"block uses operator scales {self.scales} but the geometry has {len(operators)}")
        outs = [conv(x, operators[s]) for conv, s in zip(self.convs, self.scales)]
        y = outs[0] if len(outs) == 1 else torch.cat(outs, dim=1)
        return self.act(self.norm(y))


class ZerNet(ZerNetBase):
    r"""Single-scale ZerNet (paper section 4.1): ``[Lin(input_width), σ] -> (ZernikeConv(w_i), [norm], σ)_i
    -> Lin(widths[-1]), σ -> Dropout -> Lin(out_channels)``.

    Args:
        in_channels, out_channels, widths, task, n_max, angular_resolution, pooling, activation, dropout,
        norm, input_width, input_skip: as :class:`~zernet.nn.models.base.ZerNetBase`.
        scale: which of ``geometry.operators`` the convolutions use (0).

    Shapes: ``x`` ``(N, C_in)``, ``geometry.operators[scale]`` -> ``(N, C_out)`` unnormalised scores.
    """

    def init_block(self, index: int, in_channels: int, out_channels: int, scale: int = 0) -> nn.Module:
        return ZernikeBlock(
            in_channels,
            out_channels,
            scales=(scale,),
            activation=self.activation,
            norm=self.norm_name,
            **self.conv_options,
        )


class MultiScaleZerNet(ZerNetBase):
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
        norm, input_width, input_skip: as :class:`~zernet.nn.models.base.ZerNetBase`.
        n_scales: number of operators used (3).
        wiring: ``"parallel"`` or ``"sequential"``.

    Shapes: ``x`` ``(N, C_in)``, ``geometry.operators[0..n_scales-1]`` -> ``(N, C_out)``.
    """

    def init_block(
        self, index: int, in_channels: int, out_channels: int, n_scales: int = 3, wiring: str = "parallel"
    ) -> nn.Module:
        if wiring not in ("parallel", "sequential"):
            raise ValueError(f"wiring must be 'parallel' or 'sequential', got {wiring!r}")
        self.n_scales, self.wiring = int(n_scales), wiring
        scales = tuple(range(self.n_scales)) if wiring == "parallel" else (min(index, self.n_scales - 1),)
        return ZernikeBlock(
            in_channels,
            out_channels,
            scales=scales,
            activation=self.activation,
            norm=self.norm_name,
            **self.conv_options,
        )
