r"""The direction-preserving ZerNet (paper section 4.4): :class:`DirectionalZerNet`."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from zernet.nn.directional import DirectionalLayerNorm, DirectionalPooling, DirectionalReLU, DirectionalZernikeConv
from zernet.zernike import n_max_for

from .base import SurfaceModel, resolve_widths

__all__ = ["DirectionalZerNet"]


class DirectionalZerNet(SurfaceModel):
    r"""ZerNet with direction-preserving convolutions (paper section 4.4).

    ``DirectionalLifting(w_0) -> [norm] -> act -> (DirectionalZernikeConv(w_i), [norm], act)_i ->
    DirectionalZernikeConv(w_last, final_order) -> [norm] -> DirectionalPooling -> ReLU -> Lin(widths[-1]), ReLU
    -> Dropout -> Lin(out_channels)``

    Between convolution blocks every feature keeps its direction axis as Fourier coefficients of order
    ``L`` (default ``(s - 1) // 2``: ``L = 1`` at the paper's ``s = 4``); ``act`` is
    :class:`DirectionalReLU`. The last convolution keeps its response up to Fourier order ``final_order``
    (default: the whole response, order ``n_max + L``), which ``pooling`` reduces to scalars. Every order
    is exactly equivariant, so a truncated response keeps the model invariant; it only pools a smoother
    function of the direction. ``final_order = 1`` makes the last layer compute 35 of its 63 input
    harmonics and 3 of its 13 output slabs (its cost near the single-scale layer's), and its continuous
    max is closed-form (``a_0 + |(a_1, b_1)|``). At the default widths this is the paper's
    ``Conv64 -> Conv128 -> Conv256 -> Lin512 -> Lin(C)``.

    Args:
        in_channels: ``C_in``.
        out_channels: ``C_out``.
        widths: convolution widths followed by the hidden linear width.
        k: Zernike bases per patch (21 in the paper).
        angular_resolution: ``s`` (4 in the paper).
        order: ``L`` of the directional features; default ``(s - 1) // 2``.
        pooling: ``"continuous"`` (default), ``"discrete"`` or ``"mean"`` at the end.
        nonlinearity: ``"regular"`` (ReLU at the ``s`` angles, default) or ``"norm"``.
        dropout: dropout probability before the output layer.
        norm: ``None`` (paper) or ``"layer"``: :class:`~zernet.nn.directional.DirectionalLayerNorm` after every
            convolution (equivariant for every rotation; a batch norm has no equivariant form here).
        final_order: Fourier order kept by the last convolution (``None``: ``n_max + L``, the whole
            response; ``configs/faust_directional.yaml`` uses 1).

    Attributes:
        directional_order: ``L`` (also ``order``): ``geometry.directional[0]`` must be the
            :class:`~zernet.operators.DirectionalOperator` of that order of ``geometry.operators[0]``
            (``geometry.with_directional(L)``, built when the data are prepared).

    Shapes:
        - input: ``x`` ``(N, C_in)``; ``geometry.operators[0]`` the single-scale patch operator and
          ``geometry.directional[0]`` its directional operator of order ``L``.
        - output: ``(N, C_out)``.
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        widths: Sequence[int] = (64, 128, 256, 512),
        k: int = 21,
        angular_resolution: int = 4,
        order: int | None = None,
        pooling: str = "continuous",
        nonlinearity: str = "regular",
        dropout: float = 0.25,
        final_order: int | None = None,
        norm: str | None = None,
    ) -> None:
        super().__init__()
        widths = resolve_widths(widths, None)
        self.in_channels = int(in_channels)
        self.out_channels = int(out_channels)
        self.widths = widths
        n_max = n_max_for(int(k))
        s = int(angular_resolution)
        order = self.directional_order_for(angular_resolution=s, order=order)
        self.order = self.directional_order = order
        self.final_order = None if final_order is None else int(final_order)
        if self.final_order is not None and self.final_order < 0:
            raise ValueError(f"final_order must be >= 0, got {final_order}")
        if norm not in (None, "none", "layer"):
            raise ValueError(
                f"{type(self).__name__}: norm must be None or 'layer' (batch norm has no "
                f"rotation-equivariant form for directional channels), got {norm!r}"
            )
        self.norm_name = None if norm in (None, "none") else norm
        conv_widths = widths[:-1]
        self.convs = nn.ModuleList()
        self.norms = nn.ModuleList()
        self.acts = nn.ModuleList()
        channels, in_order = self.in_channels, 0
        for i, width in enumerate(conv_widths):
            last = i == len(conv_widths) - 1
            out_order = order
            if last:
                out_order = n_max + in_order if self.final_order is None else self.final_order
            self.convs.append(DirectionalZernikeConv(channels, width, n_max=n_max, order=in_order, out_order=out_order))
            self.norms.append(DirectionalLayerNorm(width) if self.norm_name else nn.Identity())
            if not last:
                self.acts.append(DirectionalReLU(width, order, mode=nonlinearity, angular_resolution=s))
            channels, in_order = width, order
        self.pool = DirectionalPooling(pooling, angular_resolution=s)
        self.hidden = nn.Linear(channels, widths[-1])
        self.dropout = nn.Dropout(dropout)
        self.output = nn.Linear(widths[-1], out_channels)

    @classmethod
    def directional_order_for(cls, angular_resolution: int = 4, order: int | None = None, **options) -> int:
        """``order``, by default ``(angular_resolution - 1) // 2``."""
        return (int(angular_resolution) - 1) // 2 if order is None else int(order)

    def forward(self, x: Tensor, geometry) -> Tensor:
        """``x`` ``(N, C_in)``, ``geometry.operators[0]`` and ``geometry.directional[0]`` -> ``(N, C_out)``."""
        self.check_features(x)
        directional = self.directional_operator(geometry)
        h = x
        for i, conv in enumerate(self.convs):
            h = self.norms[i](conv(h, geometry.operators[0] if i == 0 else directional))
            if i < len(self.acts):
                h = self.acts[i](h)
        h = torch.relu(self.pool(h))
        h = torch.relu(self.hidden(h))
        return self.output(self.dropout(h))

    def directional_operator(self, geometry):
        """``geometry.directional[0]``, checked to be of this model's order (``ValueError`` naming the fix)."""
        have = getattr(geometry, "directional_order", None)
        if have != self.order:
            has = "none" if have is None else f"order {have}"
            raise ValueError(
                f"{type(self).__name__}: the geometry was built without directional operators of order "
                f"L={self.order} (it has {has}): call geometry.with_directional({self.order}) "
                f"(zernet.operators.Geometry.with_directional) when preparing the data"
            )
        return geometry.directional[0]
