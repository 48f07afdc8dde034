"""Reference models that zernet is measured against, in the same harness (issue 5).

Both share zernet's model signature ``model(x (N, C_in), geometry) -> (N, C_out)``, its options for widths
(``widths`` or ``task``), activation and dropout, and are registered in
:mod:`zernet.nn.models.registry`, so training, evaluation and the benchmark report select them by
name (``model.name: feastnet``) like any zernet model.

``"feastnet"`` — :class:`FeaStNet`
    Verma et al. 2018, "FeaStNet: Feature-Steered Graph Convolutions for 3D Shape Analysis", built on
    PyTorch Geometric's :class:`torch_geometric.nn.FeaStConv` (the library's layer, not a rewrite). It
    convolves over the mesh edge graph (``geometry.edge_index``) with self-loops added, as FeaStNet does.
    Settings from the FeaStNet paper's single-scale FAUST network
    (``Lin16 -> Conv32 -> Conv64 -> Conv128 -> Lin256 -> Lin(C)``): a linear input layer to 16 features
    before the first convolution, ``M = 8`` feature-steering heads, translation-invariant steering weights
    ``q_h = softmax_h(u_h^T (x_j - x_i) + c_h)`` (the variant ``FeaStConv`` implements, and the one the
    FeaStNet paper reports best on FAUST), mean aggregation over the neighbourhood including the vertex
    itself, ReLU. The convolution and linear widths are by default zernet's for the task (the ZerNet
    paper's single-scale ``(64, 128, 256, 512)`` for correspondence), so that both methods are compared at
    equal widths; ``widths=(32, 64, 128, 256)`` gives FeaStNet's own network. Dropout sits before the output
    layer, where zernet's models put it.

The ZerNet paper's own discretisation, ``"paper-zernet"``, is in :mod:`zernet.nn.models.paper`.
"""

from __future__ import annotations

from collections.abc import Sequence

from torch import Tensor, nn

from .base import SurfaceModel, activation_module, resolve_widths

__all__ = ["FeaStNet"]


class FeaStNet(SurfaceModel):
    r"""FeaStNet (Verma et al. 2018) on PyTorch Geometric's :class:`~torch_geometric.nn.FeaStConv`.

    ``x -> [Lin(input_width), σ] -> (FeaStConv(w_i, heads), σ)_i -> Lin(widths[-1]), σ -> Dropout
    -> Lin(out_channels)``

    .. math::
        \mathbf{x}'_i = \frac{1}{|\mathcal{N}(i) \cup \{i\}|} \sum_{j \in \mathcal{N}(i) \cup \{i\}}
            \sum_{h=1}^{M} q_h(\mathbf{x}_i, \mathbf{x}_j)\, W_h \mathbf{x}_j + \mathbf{b},\qquad
        q_h = \operatorname{softmax}_h\big(\mathbf{u}_h^\top(\mathbf{x}_j - \mathbf{x}_i) + c_h\big)

    Args:
        in_channels: input features per vertex ``C_in`` (e.g. 3 for xyz).
        out_channels: outputs per vertex ``C_out`` (classes, or 1 for regression).
        widths: convolution widths followed by the hidden linear width; default from ``task`` (zernet's
            table: ``(64, 128, 256, 512)`` for correspondence). FeaStNet's own FAUST network is
            ``(32, 64, 128, 256)``.
        task: ``"correspondence"``, ``"segmentation"`` or ``"regression"``: zernet's widths for the task
            when ``widths`` is not given.
        heads: feature-steering heads ``M`` per convolution (FeaStNet: 8).
        input_width: width of the linear layer before the first convolution (FeaStNet: 16); ``None`` or
            ``0`` convolves the raw input features directly.
        activation: ``"relu"`` (FeaStNet) or ``"elu"``.
        dropout: dropout probability before the output layer (0.25, as zernet's models).
        add_self_loops: include the vertex itself in its neighbourhood (FeaStNet does).

    Shapes:
        - input: ``x`` ``(N, C_in)``; ``geometry.edge_index`` ``(2, E)`` mesh edges in both directions
          (a batch of surfaces: block-diagonal, no edges between surfaces).
        - output: ``(N, C_out)`` unnormalised scores (or regression values).
    """

    #: It reads only ``geometry.edge_index``: its runs build no patch operators.
    reads_patch_operators = False

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        widths: Sequence[int] | None = None,
        task: str | None = None,
        heads: int = 8,
        input_width: int | None = 16,
        activation: str = "relu",
        dropout: float = 0.25,
        add_self_loops: bool = True,
    ) -> None:
        # Imported here, not with the module: torch_geometric's import compiles TorchScript classes
        # (seconds; on a CUDA machine tens of seconds), which every zernet command would otherwise pay.
        from torch_geometric.nn import FeaStConv

        super().__init__()
        if int(heads) < 1:
            raise ValueError(f"heads must be >= 1, got {heads}")
        self.in_channels = int(in_channels)
        self.out_channels = int(out_channels)
        self.widths = resolve_widths(widths, task)
        self.heads = int(heads)
        self.act = activation_module(activation)
        self.input = nn.Linear(self.in_channels, int(input_width)) if input_width else None
        channels = int(input_width) if input_width else self.in_channels
        self.convs = nn.ModuleList()
        for width in self.widths[:-1]:
            self.convs.append(FeaStConv(channels, width, heads=self.heads, add_self_loops=add_self_loops))
            channels = width
        self.hidden = nn.Linear(channels, self.widths[-1])
        self.dropout = nn.Dropout(dropout)
        self.output = nn.Linear(self.widths[-1], self.out_channels)

    def forward(self, x: Tensor, geometry) -> Tensor:
        """``x`` ``(N, C_in)``, ``geometry.edge_index`` ``(2, E)`` -> ``(N, C_out)``."""
        self.check_features(x)
        edge_index = getattr(geometry, "edge_index", None)
        if edge_index is None:
            raise ValueError(
                "feastnet convolves over a graph but geometry.edge_index is None: give the Geometry the mesh "
                "edges in both directions (zernet.data.preprocess.mesh_edge_index builds them, or a k-NN "
                "graph for a point cloud)"
            )
        edge_index = edge_index.to(device=x.device)
        if self.input is not None:
            x = self.act(self.input(x))
        for conv in self.convs:
            x = self.act(conv(x, edge_index))
        x = self.act(self.hidden(x))
        return self.output(self.dropout(x))
