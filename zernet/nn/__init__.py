"""Neural-network layers on surfaces, and the models built from them.

- ``conv.py``: :class:`ZernikeConv`, the Zernike convolution through the harmonic form (``harmonic_plan``,
  ``harmonic_contraction``, ``float32_forward``).
- ``pooling.py``: angular pooling modes and the harmonic-form helpers (``trig_basis``,
  ``evaluate_harmonics``, ``discrete_max``, ``continuous_max``).
- ``directional.py``: the direction-preserving layers (``DirectionalZernikeConv``, ``DirectionalLifting``,
  ``DirectionalPooling``, ``DirectionalReLU``).
- ``directional_plan.py``: which input harmonics a direction-preserving layer needs and how they couple to
  its outputs (``directional_plan``, ``harmonic_weights``, ``plan_contraction``).
- ``reference.py``: the rotated-kernel formulation (test reference) and ``MatrixOperator``.
- ``models/``: ``build_model``, ``register_model`` and the model families.

``Geometry`` lives in :mod:`zernet.operators`; it is re-exported here for code written before it moved.
"""

from zernet.operators import Geometry

from .conv import HarmonicPlan, ZernikeConv, float32_forward, harmonic_contraction, harmonic_plan
from .directional import DirectionalLifting, DirectionalPooling, DirectionalReLU, DirectionalZernikeConv
from .models import MODEL_REGISTRY, available_models, build_model, directional_order, register_model
from .pooling import (
    POOLING_MODES,
    angular_pool,
    continuous_max,
    discrete_max,
    equispaced_angles,
    evaluate_harmonics,
    harmonic_mean,
    trig_basis,
)
from .reference import MatrixOperator, RotatedKernelConv, rotated_kernel_responses

__all__ = [
    "ZernikeConv",
    "HarmonicPlan",
    "harmonic_plan",
    "harmonic_contraction",
    "float32_forward",
    "DirectionalZernikeConv",
    "DirectionalLifting",
    "DirectionalPooling",
    "DirectionalReLU",
    "Geometry",
    "build_model",
    "register_model",
    "available_models",
    "directional_order",
    "MODEL_REGISTRY",
    "POOLING_MODES",
    "trig_basis",
    "equispaced_angles",
    "evaluate_harmonics",
    "harmonic_mean",
    "discrete_max",
    "continuous_max",
    "angular_pool",
    "MatrixOperator",
    "RotatedKernelConv",
    "rotated_kernel_responses",
]
