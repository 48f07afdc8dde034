"""Deprecated: this name now lives in :mod:`zernet.geometry.membrane` (import it from there)."""

from zernet.geometry.membrane import membrane_stress  # noqa: F401
