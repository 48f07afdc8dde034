"""Deprecated: the patch operator now lives in :mod:`zernet.operators` (``patch.py``, ``cache.py``, ``sparse.py``)."""

from zernet.operators.cache import FORMAT_VERSION, CacheWarning, cache_key
from zernet.operators.patch import (
    PatchConfig,
    PatchOperator,
    assemble_operator,
    build_patch_operator,
    fit_patches,
    select_patches,
)
from zernet.operators.sparse import SparseApply, checked_basis_order, reorder_basis_rows, to_torch_csr

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
    "reorder_basis_rows",
    "CacheWarning",
    "FORMAT_VERSION",
    "cache_key",
]
