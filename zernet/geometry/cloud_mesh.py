"""A triangle mesh through the points of a cloud, so that point clouds get surface distances.

The front propagation (:mod:`zernet.geometry.polar.front`) measures geodesic distance over triangles; a point
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
4. a triangle whose plane is more than 60 degrees from a corner's tangent plane is dropped: it stands
   across the surface, bridging two sheets closer than the point spacing (lips, eyelids, touching toes);
5. triangles are accepted most proposed first (on a smooth, well sampled surface all three corners
   propose a triangle: the local rings agree with the Delaunay triangulation), ties by the shorter
   longest edge, while none of their edges already has two triangles (edge-manifold);
6. the triangles are oriented consistently across shared edges (along a spanning tree that crosses
   folds last) and each connected piece outward by its signed volume: this corrects the cloud's normals
   where its own spanning tree flipped them, in a region (the head's fine detail) or as a whole;
7. holes of at most 12 edges, where the local rings disagreed, are closed ear by ear; longer loops (the
   rim of a partial scan) stay open.

The front only stops at holes, which truncates a patch instead of bending it through the air. Measured
in ``benchmarks/speed/bench_geodesics.py`` against exact polyhedral geodesics on the mesh the points came from.

Public API: :data:`CLOUD_MESH_NEIGHBOURS`, :func:`triangulate_cloud`, :func:`mesh_from_cloud`.
"""

from __future__ import annotations

import numba
import numpy as np
import scipy.sparse
import scipy.sparse.linalg
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from zernet.geometry.surface import Surface, SurfaceError

__all__ = ["CLOUD_MESH_NEIGHBOURS", "triangulate_cloud", "mesh_from_cloud"]

#: Neighbours among which each point's local Delaunay ring is found.
CLOUD_MESH_NEIGHBOURS = 16
# Neighbours whose normal makes more than acos(0.25) ~ 75 degrees with the point's are on a facing sheet.
_MIN_NORMAL_AGREEMENT = 0.25
# A triangle is kept only if its plane is within acos(0.5) = 60 degrees of every corner's tangent plane.
_MIN_FACE_AGREEMENT = 0.5
# Weight of the cloud's own normals against the agreement of neighbouring faces (see _orient_faces).
_ORIENTATION_PRIOR = 1e-2
# A connected piece of fewer faces is too small for its signed volume to say which side is out.
_MIN_PIECE_FACES = 20
# Boundary loops of at most this many edges are holes where the local rings disagreed: they are closed.
_MAX_HOLE_EDGES = 12


def triangulate_cloud(points: np.ndarray, normals: np.ndarray, k: int = CLOUD_MESH_NEIGHBOURS) -> np.ndarray:
    """Triangles through the points of a cloud (module docstring).

    Args:
        points: (N, 3) float64 positions, N >= 3.
        normals: (N, 3) float64 unit normals, oriented as well as a cloud allows (a whole piece flipped is
            corrected from the triangles).

    Returns:
        (F, 3) int64 triangles over the N points, turned along the normals and outward (by the signed volume
        of each connected piece). Points in no triangle are rare (isolated outliers).
    """
    points = np.ascontiguousarray(points, dtype=np.float64)
    n = len(points)
    k = min(k, n - 1)
    _, neighbours = cKDTree(points).query(points, k=k + 1)
    neighbours = np.ascontiguousarray(neighbours[:, 1:], dtype=np.int64)
    faces = _orient_faces(points, normals, _select_triangles(points, normals, neighbours))
    if len(faces) == 0:
        return faces
    # The normals of the oriented triangles: a piece may have been turned against the cloud's normals.
    return _fill_small_holes(points, Surface(points, faces).vertex_normals(), faces)


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


def _select_triangles(points: np.ndarray, normals: np.ndarray, neighbours: np.ndarray) -> np.ndarray:
    """Steps 2-5 of the module docstring: the proposed triangles, filtered and selected (unoriented)."""
    proposed = _local_rings(points, np.ascontiguousarray(normals, dtype=np.float64), neighbours, _MIN_NORMAL_AGREEMENT)
    if len(proposed) == 0:
        return np.zeros((0, 3), dtype=np.int64)
    triangles, votes = np.unique(np.sort(proposed, axis=1), axis=0, return_counts=True)
    # A triangle standing across the surface (bridging two sheets closer than the point spacing: lips,
    # eyelids, touching toes) is far from every corner's tangent plane, whatever the normals' signs.
    corners = points[triangles]
    face_normal = _unit(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]))
    lying = np.abs(np.einsum("fi,fci->fc", face_normal, normals[triangles])).min(axis=1) >= _MIN_FACE_AGREEMENT
    triangles, votes = triangles[lying], votes[lying]
    longest = np.linalg.norm(points[triangles] - points[np.roll(triangles, 1, axis=1)], axis=2).max(axis=1)
    return triangles[_edge_manifold_selection(triangles, votes, longest)]


def _orient_faces(points: np.ndarray, normals: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Faces turned to one orientation, and each connected piece outward.

    Every face agrees with its neighbours across shared edges as far as possible, smooth steps counting
    more than folds, with the cloud's normals as a weak prior (a signed-Laplacian least-squares problem,
    see the code): where the cloud's normals flipped (its spanning tree crosses thin parts and the head's
    fine detail) the triangles are still turned to agree with the surface around them. Each connected
    piece is then turned outward by
    the sign of its volume about its centroid (a one-sided partial scan bulges towards the camera, so the
    rule holds for it too); a piece of a few faces follows its corners' normals instead.
    """
    if len(faces) == 0:
        return faces
    n_faces = len(faces)
    corners = points[faces]
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    along = np.einsum("fi,fi->f", cross, normals[faces].sum(axis=1)) >= 0
    faces = np.where(along[:, None], faces, faces[:, [0, 2, 1]])
    unit = _unit(np.where(along[:, None], cross, -cross))
    # Faces sharing an edge (two faces per edge: the selection is edge-manifold).
    half = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])  # half-edge h of face h % F
    _, edge, count = np.unique(np.sort(half, axis=1), axis=0, return_inverse=True, return_counts=True)
    edge = edge.reshape(-1)
    shared = np.flatnonzero(count[edge] == 2)
    pairs = shared[np.argsort(edge[shared], kind="stable")].reshape(-1, 2)
    first, second = pairs[:, 0] % n_faces, pairs[:, 1] % n_faces
    # Consistent neighbours run through their shared edge in opposite directions.
    disagree = half[pairs[:, 0], 0] == half[pairs[:, 1], 0]
    smoothness = np.abs(np.einsum("fi,fi->f", unit[first], unit[second]))
    # Signs s_f = ±1 (keep or flip each face) minimising sum_e w_e (s_f - r_e s_g)^2 + λ sum_f (s_f - 1)^2:
    # r_e = -1 where two faces run through their edge the same way, w_e the smoothness of the step (a fold
    # or a bridging triangle weighs little), and the prior keeps the cloud's normals where nothing else
    # decides. Relaxed to real s, this is one sparse linear system (a signed graph Laplacian).
    relation = np.where(disagree, -1.0, 1.0)
    laplacian = scipy.sparse.coo_matrix(
        (
            np.concatenate([smoothness, smoothness, -smoothness * relation, -smoothness * relation]),
            (np.concatenate([first, second, first, second]), np.concatenate([first, second, second, first])),
        ),
        shape=(n_faces, n_faces),
    ).tocsc()
    signs = scipy.sparse.linalg.spsolve(
        laplacian + _ORIENTATION_PRIOR * scipy.sparse.identity(n_faces, format="csc"),
        np.full(n_faces, _ORIENTATION_PRIOR),
    )
    flip = signs < 0
    faces = np.where(flip[:, None], faces[:, [0, 2, 1]], faces)
    _, piece = connected_components(
        scipy.sparse.coo_matrix((np.ones(len(first)), (first, second)), shape=(n_faces, n_faces)), directed=False
    )
    corners = points[faces]
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    centroid = corners.mean(axis=1)
    weight_sum = np.maximum(np.bincount(piece, weights=area), 1e-300)
    middle = (
        np.stack([np.bincount(piece, weights=area * centroid[:, i]) for i in range(3)], axis=1) / weight_sum[:, None]
    )
    volume = np.bincount(piece, weights=np.einsum("fi,fi->f", centroid - middle[piece], cross))
    size = np.bincount(piece)
    inward = (volume[piece] < 0) & (size[piece] >= _MIN_PIECE_FACES)
    faces[inward] = faces[inward][:, [0, 2, 1]]
    return faces


def _fill_small_holes(points: np.ndarray, normals: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Close every simple boundary loop of at most :data:`_MAX_HOLE_EDGES` edges, ear by ear (shortest new
    edge first), with triangles oriented like their neighbours. Long loops (the rim of an open scan) stay,
    and so does a loop whose filling would face against its corners' normals (not a hole but the rim of a
    fold, whose inside is covered already)."""
    half = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    key = np.sort(half, axis=1)
    _, edge, count = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    boundary = half[count[edge.reshape(-1)] == 1]
    existing = {(int(a), int(b)) for a, b in key}
    following: dict[int, list[int]] = {}
    for a, b in boundary:
        following.setdefault(int(a), []).append(int(b))
    added = []
    used: set[int] = set()
    for start in list(following):
        if start in used or len(following[start]) != 1:
            continue
        loop = [start]
        while len(loop) <= _MAX_HOLE_EDGES:
            ahead = following.get(loop[-1], [])
            if len(ahead) != 1 or ahead[0] in used:
                break
            if ahead[0] == start:
                break
            loop.append(ahead[0])
        closed = following.get(loop[-1], [None]) == [start]
        if not closed or len(loop) < 3 or len(loop) > _MAX_HOLE_EDGES or len(set(loop)) != len(loop):
            continue
        used.update(loop)
        patch = _clip_ears(points, loop, set(existing))
        if patch:
            patch = np.asarray(patch, dtype=np.int64)
            corners = points[patch]
            cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
            if (np.einsum("fi,fi->f", cross, normals[patch].sum(axis=1)) > 0).all():
                added.extend(patch.tolist())
                existing.update((min(a, b), max(a, b)) for a, b in patch[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2).tolist())
    if not added:
        return faces
    return np.concatenate([faces, np.asarray(added, dtype=np.int64)])


def _clip_ears(points: np.ndarray, loop: list[int], existing: set) -> list[tuple[int, int, int]]:
    """Triangles filling one boundary loop (its edges run ``loop[i] -> loop[i + 1]`` in their faces)."""
    loop = list(loop)
    triangles = []
    while len(loop) > 3:
        candidates = []
        for i in range(len(loop)):
            before, after = loop[i - 1], loop[(i + 1) % len(loop)]
            if (min(before, after), max(before, after)) not in existing:
                candidates.append((np.linalg.norm(points[before] - points[after]), i))
        if not candidates:
            return []  # every diagonal is an edge already: leave the hole open rather than fold the mesh
        _, i = min(candidates)
        before, middle, after = loop[i - 1], loop[i], loop[(i + 1) % len(loop)]
        triangles.append((after, middle, before))
        existing.add((min(before, after), max(before, after)))
        loop.pop(i)
    triangles.append((loop[2], loop[1], loop[0]))
    return triangles


def _unit(vectors: np.ndarray) -> np.ndarray:
    length = np.linalg.norm(vectors, axis=1, keepdims=True)
    return np.divide(vectors, length, out=np.zeros_like(vectors), where=length > 0)


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

    Returns (T, 3) int64 triangles ``(p, a, b)``, ``p`` the proposing point.
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
    return out[:count].copy()


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
                cross = (xy[b, 0] - xy[a, 0]) * (xy[index, 1] - xy[a, 1]) - (xy[b, 1] - xy[a, 1]) * (
                    xy[index, 0] - xy[a, 0]
                )
                if cross > 0.0:
                    break
                size -= 1
            hull[size] = index
            size += 1
        size -= 1  # the last point of each chain starts the other
    return max(size, 0)
