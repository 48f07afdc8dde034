"""Deprecated: these names now live in :mod:`zernet.geometry.polar` (import them from there)."""

from zernet.geometry.polar import BACKENDS, PolarCoordinates, compute_polar, tangent_frames, transport_angles  # noqa: F401
