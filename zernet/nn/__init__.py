"""Neural-network layers and models on surfaces.

- :class:`ZernikeConv` (``conv.py``): Zernike convolution through the harmonic form, angular pooling.
- ``pooling.py``: pooling modes and the harmonic-form helpers (``trig_basis``, ``evaluate_harmonics``,
  ``discrete_max``, ``continuous_max``); ``conv.py``: ``harmonic_plan``, ``harmonic_contraction``.
- :class:`Geometry` (``geometry.py``): what a model needs about one surface or a batch of surfaces.
- ``models.py``: ``build_model``, ``register_model`` and the ZerNet models.
- ``reference.py``: the rotated-kernel formulation (test reference) and ``MatrixOperator``.
"""

from .conv import HarmonicPlan, ZernikeConv, harmonic_contraction, harmonic_plan
from .geometry import Geometry
from .models import MODEL_REGISTRY, available_models, build_model, register_model
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
    "Geometry",
    "build_model",
    "register_model",
    "available_models",
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
