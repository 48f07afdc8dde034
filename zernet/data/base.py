"""Deprecated: the containers now live in :mod:`zernet.data.dataset` and the features in :mod:`zernet.data.features`."""

from zernet.data.dataset import TASKS, DatasetError, ShapeDataset, ShapeRecord, carve_validation  # noqa: F401
from zernet.data.features import (  # noqa: F401
    BOUNDARY_SATURATION,
    FEATURE_PARTS,
    MEMBRANE_PRESTRESSES,
    compute_features,
    curvature_descriptors,
    default_features,
    feature_channels,
    feature_parts,
    membrane_descriptors,
    shape_descriptors,
)
