"""Surface geometry in float64 numpy/scipy (no torch): the :class:`Surface` data class, file reading,
validation and repair, area normalisation and sampling, point-cloud estimators, geodesic polar coordinates
and tangent frames, and the membrane-stress physics prior.

Modules, each with one job:

- :mod:`~zernet.geometry.surface` — :class:`Surface`, :class:`SurfaceError`, :class:`SurfaceWarning`.
- :mod:`~zernet.geometry.pointcloud` — array estimators for clouds (PCA normals, cell areas, curvature).
- :mod:`~zernet.geometry.io` — :func:`load_surface` and the file readers.
- :mod:`~zernet.geometry.coarsen` — :func:`coarsen_surface` (a coarse copy and where each vertex went).
- :mod:`~zernet.geometry.validate` — :func:`validate_surface`, :func:`repair_surface` and the checks.
- :mod:`~zernet.geometry.cloud_mesh` — :func:`mesh_from_cloud`: triangles through a cloud's own points.
- :mod:`~zernet.geometry.sampling` — :class:`FixedScale`, :func:`normalize_area`, :class:`SurfaceSamples`, :func:`sample_surface`.
- :mod:`~zernet.geometry.polar` (a package) — :func:`compute_polar`, :func:`tangent_frames`,
  :func:`transport_angles`, with the backends in :mod:`~zernet.geometry.polar.front` (and its vertex fans,
  :mod:`~zernet.geometry.polar.fans`), :mod:`~zernet.geometry.polar.fast`, :mod:`~zernet.geometry.polar.accurate`,
  and the exact reference in :mod:`~zernet.geometry.polar.exact`.
- :mod:`~zernet.geometry.membrane` — :func:`membrane_stress`.
"""

from zernet.geometry.cloud_mesh import mesh_from_cloud
from zernet.geometry.coarsen import CoarseCopy, coarsen_surface
from zernet.geometry.io import load_surface, read_surface
from zernet.geometry.membrane import membrane_stress
from zernet.geometry.polar import (
    BACKEND_VERSIONS,
    BACKENDS,
    PolarCoordinates,
    compute_polar,
    resolve_backend,
    tangent_frames,
    transport_angles,
)
from zernet.geometry.sampling import FixedScale, SurfaceSamples, normalize_area, sample_surface
from zernet.geometry.surface import Surface, SurfaceError, SurfaceWarning
from zernet.geometry.validate import RepairedSurface, repair_surface, validate_surface

__all__ = [
    "CoarseCopy",
    "coarsen_surface",
    "Surface",
    "SurfaceError",
    "SurfaceWarning",
    "load_surface",
    "read_surface",
    "validate_surface",
    "repair_surface",
    "RepairedSurface",
    "mesh_from_cloud",
    "FixedScale",
    "normalize_area",
    "SurfaceSamples",
    "sample_surface",
    "BACKENDS",
    "BACKEND_VERSIONS",
    "resolve_backend",
    "PolarCoordinates",
    "compute_polar",
    "tangent_frames",
    "transport_angles",
    "membrane_stress",
]
