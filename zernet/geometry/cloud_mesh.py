"""A triangle mesh through the points of a cloud, so that point clouds get surface distances.

The front propagation (:mod:`zernet.geometry.front`) measures geodesic distance over triangles; a point
cloud has none. :func:`triangulate_cloud` builds them from the points alone, keeping every point as a
vertex (so per-point features and predictions stay one per point):

1. the ``k`` nearest neighbours of every point, and oriented normals (PCA, propagated along a spanning tree:
   :meth:`zernet.geometry.Surface.vertex_normals`);
2. neighbours whose normal points away from the point's (``n_p · n_q < 0.25``) are dropped: they lie on a
   facing sheet (the other side of a thin part, a touching limb, across the crotch), and joining them is
   the shortcut through the air that a chord backend makes;
3. the *local Delaunay ring* of each point: the neighbours, projected on the point's tangent plane, whose
   half-plane bounds the point's Voronoi cell (by polar duality, the vertices of the convex hull of the
   inverted offsets ``2 q / |q|²`` and the origin); consecutive ring members, by angle, span a triangle
   unless the angular gap reaches π (an open rim);
4. a triangle is kept when at least two of its corners propose it (on a smooth, well sampled surface all
   three do: the local rings agree with the Delaunay triangulation); a point that ends up in no kept
   triangle keeps the triangles it proposed itself, so that no point is left without a patch. Every
   triangle is oriented along its corners' normals.

The result may have a few non-manifold edges and small holes where the local rings disagree; the front
handles both (it moves over faces around vertices, not along a half-edge structure) and only stops at
holes, which truncates a patch instead of bending it through the air. Measured in
``benchmarks/bench_geodesics.py`` against exact polyhedral geodesics on the mesh the points came from.

Public API: :data:`CLOUD_MESH_NEIGHBOURS`, :func:`triangulate_cloud`, :func:`mesh_from_cloud`.
"""

from __future__ import annotations

import numba
import numpy as np
from scipy.spatial import cKDTree

from zernet.geometry.surface import Surface, SurfaceError

__all__ = ["CLOUD_MESH_NEIGHBOURS", "triangulate_cloud", "mesh_from_cloud"]

#: Neighbours among which each point's local Delaunay ring is found.
CLOUD_MESH_NEIGHBOURS = 16
# Neighbours whose normal makes more than acos(0.25) ~ 75 degrees with the point's are on a facing sheet.
_MIN_NORMAL_AGREEMENT = 0.25
# Votes (corners proposing it) a triangle needs to be kept.
_MIN_VOTES = 2


def triangulate_cloud(points: np.ndarray, normals: np.ndarray, k: int = CLOUD_MESH_NEIGHBOURS) -> np.ndarray:
    """Triangles through the points of a cloud (module docstring).

    Args:
        points: (N, 3) float64 positions, N >= 3.
        normals: (N, 3) float64 consistently oriented unit normals.
        k: neighbours per point among which its local Delaunay ring is found.

    Returns:
        (F, 3) int64 triangles over the N points, each oriented so that its normal agrees with the sum of
        its corners' normals. Points may be shared by non-manifold edges; points in no triangle are rare
        (isolated outliers).
    """
    points = np.ascontiguousarray(points, dtype=np.float64)
    normals = np.ascontiguousarray(normals, dtype=np.float64)
    n = len(points)
    k = min(k, n - 1)
    _, neighbours = cKDTree(points).query(points, k=k + 1)
    neighbours = np.ascontiguousarray(neighbours[:, 1:], dtype=np.int64)
    proposed, proposer = _local_rings(points, normals, neighbours, _MIN_NORMAL_AGREEMENT)
    if len(proposed) == 0:
        return np.zeros((0, 3), dtype=np.int64)
    triangles, votes = np.unique(np.sort(proposed, axis=1), axis=0, return_counts=True)
    longest = np.linalg.norm(points[triangles] - points[np.roll(triangles, 1, axis=1)], axis=2).max(axis=1)
    triangles = triangles[_edge_manifold_selection(triangles, votes, longest)]
    # Orient every triangle along its corners' normals.
    a, b, c = (points[triangles[:, i]] for i in range(3))
    facing = np.einsum("fi,fi->f", np.cross(b - a, c - a), normals[triangles].sum(axis=1))
    triangles[facing < 0] = triangles[facing < 0][:, [0, 2, 1]]
    return triangles


def mesh_from_cloud(surface: Surface, k: int = CLOUD_MESH_NEIGHBOURS) -> Surface:
    """The mesh of :func:`triangulate_cloud` through a point cloud's points: same vertices (same order),
    normals, fields and name; a mesh is returned unchanged."""
    if not surface.is_point_cloud:
        return surface
    if surface.n_vertices < 3:
        raise SurfaceError(f"{surface.name}: a point cloud needs at least 3 points, got {surface.n_vertices}")
    faces = triangulate_cloud(surface.vertices, surface.vertex_normals(), k)
    if len(faces) == 0:
        raise SurfaceError(f"{surface.name}: no triangle could be formed through the points (all collinear?)")
    return Surface(surface.vertices, faces, surface.normals, surface.fields, surface.name)


def _edge_manifold_selection(triangles: np.ndarray, votes: np.ndarray, longest: np.ndarray) -> np.ndarray:
    """(T,) mask of the triangles kept: most votes first (ties: the shorter longest edge first), each
    accepted while none of its edges already has two triangles."""
    edges = np.sort(triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    _, edge_id = np.unique(edges, axis=0, return_inverse=True)
    order = np.lexsort((longest, -votes))
    return _greedy_accept(edge_id.reshape(-1, 3).astype(np.int64), order.astype(np.int64))


@numba.njit(cache=True)
def _greedy_accept(triangle_edges, order):
    """Accept triangles in ``order`` while each of their edges has fewer than two accepted triangles."""
    uses = np.zeros(triangle_edges.max() + 1, dtype=np.int64)
    keep = np.zeros(len(triangle_edges), dtype=np.bool_)
    for t in order:
        a, b, c = triangle_edges[t, 0], triangle_edges[t, 1], triangle_edges[t, 2]
        if uses[a] < 2 and uses[b] < 2 and uses[c] < 2:
            keep[t] = True
            uses[a] += 1
            uses[b] += 1
            uses[c] += 1
    return keep


@numba.njit(cache=True)
def _local_rings(points, normals, neighbours, min_agreement):
    """The triangles each point proposes: its local Delaunay ring (module docstring, step 3).

    Returns ``(triangles, proposer)``: (T, 3) int64 ``(p, a, b)`` and (T,) the proposing point ``p``.
    """
    n, k = neighbours.shape
    out = np.empty((n * k, 3), dtype=np.int64)
    count = 0
    inverted = np.empty((k + 1, 2))
    angle = np.empty(k)
    member = np.empty(k, dtype=np.int64)
    on_hull = np.empty(k + 1, dtype=np.bool_)
    hull = np.empty(2 * (k + 1), dtype=np.int64)
    for p in range(n):
        normal = normals[p]
        # A tangent basis (t1, t2) of p's normal.
        if abs(normal[0]) < 0.9:
            helper = np.array([1.0, 0.0, 0.0])
        else:
            helper = np.array([0.0, 1.0, 0.0])
        t1 = np.cross(normal, helper)
        t1 /= np.sqrt(t1 @ t1)
        t2 = np.cross(normal, t1)
        m = 0
        for slot in range(k):
            q = neighbours[p, slot]
            if normals[q] @ normal < min_agreement:
                continue
            offset = points[q] - points[p]
            x, y = offset @ t1, offset @ t2
            square = x * x + y * y
            if square <= 1e-300:
                continue
            inverted[m, 0], inverted[m, 1] = 2.0 * x / square, 2.0 * y / square
            angle[m] = np.arctan2(y, x)
            member[m] = q
            m += 1
        if m < 2:
            continue
        inverted[m, 0], inverted[m, 1] = 0.0, 0.0  # the origin (p itself) joins the hull
        size = _hull(inverted[: m + 1], hull)
        on_hull[: m + 1] = False
        for h in range(size):
            on_hull[hull[h]] = True
        ring = [i for i in range(m) if on_hull[i]]
        if len(ring) < 2:
            continue
        ring_angle = np.array([angle[i] for i in ring])
        order = np.argsort(ring_angle)
        for position in range(len(order)):
            i = ring[order[position]]
            j = ring[order[(position + 1) % len(order)]]
            gap = angle[j] - angle[i]
            if gap <= 0.0:
                gap += 2.0 * np.pi
            if gap < np.pi and i != j:
                out[count, 0], out[count, 1], out[count, 2] = p, member[i], member[j]
                count += 1
    proposer = out[:count, 0].copy()
    return out[:count].copy(), proposer


@numba.njit(cache=True)
def _hull(xy, hull):
    """Indices of the convex hull vertices of the 2D points ``xy`` (Andrew's monotone chain, collinear
    points left out) written into ``hull``; returns their count."""
    by_y = np.argsort(xy[:, 1], kind="mergesort")
    order = by_y[np.argsort(xy[by_y, 0], kind="mergesort")]  # by x, ties by y
    size = 0
    for pass_ in range(2):
        start = size
        sequence = order if pass_ == 0 else order[::-1]
        for index in sequence:
            while size >= start + 2:
                a, b = hull[size - 2], hull[size - 1]
                cross = (xy[b, 0] - xy[a, 0]) * (xy[index, 1] - xy[a, 1]) - (xy[b, 1] - xy[a, 1]) * (xy[index, 0] - xy[a, 0])
                if cross > 0.0:
                    break
                size -= 1
            hull[size] = index
            size += 1
        size -= 1  # the last point of each chain starts the other
    return max(size, 0)
