"""Deprecated: :class:`Geometry` now lives in :mod:`zernet.operators` (``zernet.operators.batch``)."""

from zernet.operators.batch import Geometry

__all__ = ["Geometry"]
