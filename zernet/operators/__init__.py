"""Per-surface linear maps, where torch starts: patch operators, their cache, directional operators and
the :class:`Geometry` a model receives.

- ``patch.py``: :class:`PatchConfig`, :class:`PatchOperator`, :func:`build_patch_operator` and its stages.
- ``sparse.py``: :class:`SparseApply` (sparse products with a stored transpose) and CSR conversions.
- ``cache.py``: the on-disk cache of patch operators (:func:`cache_key`, the checked file format).
- ``directional.py``: :class:`DirectionalOperator` and :func:`build_directional_operator`.
- ``harmonic_csr.py``: the compiled kernels that write a directional operator's matrix and its transpose.
- ``batch.py``: :class:`Geometry`, one surface or a block-diagonal batch.
- ``spectral.py``: the Laplace-Beltrami eigenbasis (cached) and point maps from functional maps and back,
  ZoomOut (imported from there: scipy's eigensolver and robust-laplacian load only when used).
"""

from .batch import Geometry
from .cache import FORMAT_VERSION, CacheWarning, cache_key
from .directional import DirectionalOperator, build_directional_operator
from .patch import PatchConfig, PatchOperator, assemble_operator, build_patch_operator, fit_patches, select_patches
from .sparse import SparseApply, basis_orders_of_size, checked_basis_order, reorder_basis_rows, to_torch_csr

__all__ = [
    "PatchConfig",
    "PatchOperator",
    "build_patch_operator",
    "select_patches",
    "fit_patches",
    "assemble_operator",
    "SparseApply",
    "to_torch_csr",
    "checked_basis_order",
    "basis_orders_of_size",
    "reorder_basis_rows",
    "CacheWarning",
    "FORMAT_VERSION",
    "cache_key",
    "DirectionalOperator",
    "build_directional_operator",
    "Geometry",
]
