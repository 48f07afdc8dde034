"""A coarse copy of a surface with about a given number of vertices, and where each vertex went.

A model trained on coarse surfaces (the matcher's descriptor model reads bodies of about 1,200 vertices)
reads a fine one through its coarse copy: the patch operators and the network's passes then cost what
they cost in training, and the answer is carried back to every vertex of the fine surface through
:attr:`CoarseCopy.nearest`.

- a mesh: quadric edge-collapse decimation (``fast_simplification``), repaired like any input;
- a point cloud: farthest-point sampling of its points (evenly spread, whatever the input's density).

Public API: :class:`CoarseCopy`, :func:`coarsen_surface`, :func:`farthest_points`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from zernet.geometry.surface import Surface
from zernet.geometry.validate import validate_surface

__all__ = ["CoarseCopy", "coarsen_surface", "farthest_points"]


@dataclass
class CoarseCopy:
    """A coarse copy of a surface.

    Attributes:
        surface: the copy (a mesh for a mesh, a point cloud for a point cloud), in the same coordinates.
        nearest: (N,) int64, for each vertex of the original surface, the copy's vertex nearest to it.
    """

    surface: Surface
    nearest: np.ndarray


def coarsen_surface(surface: Surface, n_vertices: int) -> CoarseCopy:
    """A copy of ``surface`` with about ``n_vertices`` vertices (module docstring)."""
    if n_vertices < 4:
        raise ValueError(f"a coarse copy needs at least 4 vertices, got {n_vertices}")
    if surface.is_point_cloud:
        keep = farthest_points(surface.vertices, min(n_vertices, surface.n_vertices))
        normals = None if surface.normals is None else surface.normals[keep]
        coarse = Surface(surface.vertices[keep], None, normals, name=surface.name)
    else:
        import fast_simplification

        # A closed mesh has about twice as many faces as vertices.
        reduction = max(0.0, 1.0 - 2.0 * n_vertices / len(surface.faces))
        vertices, faces = fast_simplification.simplify(
            surface.vertices.astype(np.float32), surface.faces.astype(np.int32), target_reduction=reduction
        )
        decimated = Surface(np.asarray(vertices, np.float64), np.asarray(faces, np.int64), name=surface.name)
        coarse = validate_surface(decimated, repair=True)  # a simplifier can leave degenerate faces
    _, nearest = cKDTree(coarse.vertices).query(surface.vertices)
    return CoarseCopy(coarse, np.asarray(nearest, dtype=np.int64))


def farthest_points(points: np.ndarray, count: int, start: int = 0) -> np.ndarray:
    """(count,) int64 indices of ``points`` (N, 3) chosen one by one, each the farthest from those chosen."""
    chosen = np.empty(count, dtype=np.int64)
    distance = np.full(len(points), np.inf)
    chosen[0] = start
    for i in range(1, count):
        distance = np.minimum(distance, np.linalg.norm(points - points[chosen[i - 1]], axis=1))
        chosen[i] = int(np.argmax(distance))
    return chosen
