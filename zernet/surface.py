"""Deprecated: these names now live in :mod:`zernet.geometry` (import them from there)."""

from zernet.geometry.io import load_surface  # noqa: F401
from zernet.geometry.sampling import SurfaceSamples, normalize_area, sample_surface  # noqa: F401
from zernet.geometry.surface import Surface, SurfaceError, SurfaceWarning  # noqa: F401
from zernet.geometry.validate import validate_surface  # noqa: F401
