"""The models on surfaces and their registry.

- ``registry.py``: :func:`build_model`, :func:`register_model`, :data:`MODEL_REGISTRY`,
  :func:`directional_order`, :func:`reads_patch_operators`.
- ``base.py``: :class:`SurfaceModel` (the model contract), :class:`ZerNetBase` (the constructor the ZerNet
  families share), default widths per task and the small module helpers.
- ``zernet.py``: :class:`ZerNet`, :class:`MultiScaleZerNet` and their :class:`ZernikeBlock`.
- ``directional.py``: :class:`DirectionalZerNet`.
- ``baselines.py``: :class:`FeaStNet`; ``paper.py``: the paper's own formulation, :class:`PaperZerNet`.
"""

from .base import (
    TASK_WIDTHS,
    SurfaceModel,
    ZerNetBase,
    activation_module,
    norm_module,
    resolve_widths,
    split_width,
)
from .baselines import FeaStNet
from .directional import DirectionalZerNet
from .paper import PaperZerNet, PaperZernikeConv, ridge_normal_matrix
from .registry import (
    MODEL_REGISTRY,
    available_models,
    build_model,
    directional_order,
    reads_patch_operators,
    register_model,
)
from .zernet import MultiScaleZerNet, ZerNet, ZernikeBlock

__all__ = [
    "MODEL_REGISTRY",
    "register_model",
    "available_models",
    "build_model",
    "directional_order",
    "reads_patch_operators",
    "TASK_WIDTHS",
    "resolve_widths",
    "activation_module",
    "norm_module",
    "split_width",
    "SurfaceModel",
    "ZerNetBase",
    "ZernikeBlock",
    "ZerNet",
    "MultiScaleZerNet",
    "DirectionalZerNet",
    "FeaStNet",
    "PaperZernikeConv",
    "PaperZerNet",
    "ridge_normal_matrix",
]
