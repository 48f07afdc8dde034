"""The ``"fast"`` polar backend: a k-d tree ball query, a chord-to-arc radius, a bend-corrected tangent
angle and a same-sheet test (see :mod:`zernet.geometry.polar` for the method).

Public API: :func:`ball_pairs` (also the candidate pairs of the accurate backend), :func:`fast_polar`,
:func:`same_sheet`.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from zernet.geometry.sampling import SurfaceSamples
from zernet.geometry.surface import Surface

__all__ = ["ball_pairs", "fast_polar", "same_sheet"]

# Point clouds: k-nearest-neighbour graph used for the sheet test, and the largest allowed |d·n| / |d|
# of a graph edge (an edge that leaves the tangent plane steeply jumps between sheets).
_CLOUD_GRAPH_NEIGHBOURS = 6
_CLOUD_GRAPH_MAX_SLOPE = 0.5
# Entries of the dense (vertex block × N) node table of the sheet test: 8 M int64 = 64 MB at most.
_TABLE_ENTRIES = 2**23


def ball_pairs(points: np.ndarray, sample_points: np.ndarray, r0: float):
    """All (vertex, sample) pairs within Euclidean distance ``r0``, sorted by vertex (stable).

    Returns:
        (center, sample, chord_length), each (P,): int64, int64, float64.
    """
    pairs = cKDTree(points).sparse_distance_matrix(cKDTree(sample_points), r0, output_type="ndarray")
    # sparse_distance_matrix drops zero distances (a sample exactly on a vertex): add those back.
    zero_center, zero_sample = _exact_coincidences(points, sample_points)
    center = np.concatenate([pairs["i"].astype(np.int64), zero_center])
    sample = np.concatenate([pairs["j"].astype(np.int64), zero_sample])
    chord_length = np.concatenate([pairs["v"], np.zeros(len(zero_center))])
    order = np.argsort(center, kind="stable")
    return center[order], sample[order], chord_length[order]


def fast_polar(surface: Surface, samples: SurfaceSamples, frames: np.ndarray, r0: float):
    """Ball query + chord-to-arc radius + bend-corrected tangent angle + same-sheet test.

    Returns:
        (center, sample, radius, angle) of the pairs with radius ``<= r0``, sorted by center.
    """
    points = surface.vertices
    center, sample, chord_length = ball_pairs(points, samples.points, r0)
    keep = same_sheet(surface, samples, center, sample, r0)
    center, sample, chord_length = center[keep], sample[keep], chord_length[keep]

    normal = frames[center, 2]
    chord = samples.points[sample] - points[center]
    height = np.einsum("pi,pi->p", chord, normal)  # signed offset along p's normal

    # Radius: arc of the circle tangent to p's plane through the sample (see zernet.geometry.polar).
    sine = np.clip(np.abs(height) / np.maximum(chord_length, 1e-300), 0.0, 1.0)
    arc_factor = np.ones_like(sine)
    bent = sine > 1e-8
    arc_factor[bent] = np.arcsin(sine[bent]) / sine[bent]
    radius = chord_length * arc_factor

    # Angle: tangent projection of the chord with its third-order bend removed.
    sample_normals = _smooth_sample_normals(surface, samples)
    direction = chord - (height / 3.0)[:, None] * (sample_normals[sample] - normal)
    angle = np.arctan2(
        np.einsum("pi,pi->p", direction, frames[center, 1]),
        np.einsum("pi,pi->p", direction, frames[center, 0]),
    )
    inside = radius <= r0
    return center[inside], sample[inside], radius[inside], angle[inside]


def _exact_coincidences(points: np.ndarray, sample_points: np.ndarray):
    """(vertex, sample) pairs at distance exactly 0, which scipy's sparse distance matrix omits."""
    distance, nearest = cKDTree(points).query(sample_points)
    hit = np.flatnonzero(distance == 0)
    if hit.size == 0:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty
    # A sample can coincide with several duplicate vertices; collect them all.
    groups = cKDTree(points).query_ball_point(sample_points[hit], 0.0)
    vertex = np.concatenate([np.asarray(g, dtype=np.int64) for g in groups])
    sample = np.repeat(hit, [len(g) for g in groups])
    return vertex, sample


def _smooth_sample_normals(surface: Surface, samples: SurfaceSamples) -> np.ndarray:
    """(M, 3) unit normals at the samples interpolated from the vertex normals (smooth, unlike face normals)."""
    normals = samples.interpolation @ surface.vertex_normals()
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    fallback = length[:, 0] < 1e-12
    normals = np.divide(normals, length, out=np.zeros_like(normals), where=~fallback[:, None])
    normals[fallback] = samples.normals[fallback]
    return normals


# ====================================================================== same-sheet test
def _surface_graph(surface: Surface) -> tuple[np.ndarray, float]:
    """Undirected vertex graph used for the sheet test: (E, 2) edges and the longest edge length.

    Mesh: its edges. Point cloud: the 6-nearest-neighbour graph without edges that leave a point's
    tangent plane steeply (|d·n| > 0.5 |d|), which would jump between the two sides of a thin part.
    """
    points = surface.vertices
    if not surface.is_point_cloud:
        edges = surface.edges()
    else:
        normals = surface.vertex_normals()
        k = min(_CLOUD_GRAPH_NEIGHBOURS, points.shape[0] - 1)
        _, index = cKDTree(points).query(points, k=k + 1)
        rows = np.repeat(np.arange(points.shape[0]), k)
        cols = index[:, 1:].ravel()
        offset = points[cols] - points[rows]
        length = np.linalg.norm(offset, axis=1)
        slope = np.maximum(
            np.abs(np.einsum("ei,ei->e", offset, normals[rows])),
            np.abs(np.einsum("ei,ei->e", offset, normals[cols])),
        )
        flat = slope <= _CLOUD_GRAPH_MAX_SLOPE * length
        edges = np.unique(np.sort(np.stack([rows[flat], cols[flat]], axis=1), axis=1), axis=0)
    if len(edges) == 0:
        return edges.reshape(0, 2), 0.0
    longest = float(np.linalg.norm(points[edges[:, 0]] - points[edges[:, 1]], axis=1).max())
    return edges, longest


def same_sheet(
    surface: Surface, samples: SurfaceSamples, center: np.ndarray, sample: np.ndarray, r0: float
) -> np.ndarray:
    """Mask of (vertex p, sample j) pairs where j is reachable from p through the surface near p.

    For every vertex p, take the vertices within ``r0 + h`` of p (``h`` = longest graph edge) and the graph
    edges between them; j is kept if the graph node it belongs to (the first vertex of its triangle, or
    the point itself in a cloud) lies in the same connected piece of that restricted graph as p. A
    geodesic of length ``<= r0`` stays within Euclidean ``r0`` of p, and every triangle it crosses has all
    its vertices within ``r0 + h``, so no true neighbour is lost; pieces that only come close in space (the
    far wall of a thin part, a touching limb, another component) are separated.

    All vertices are done at once: one graph whose nodes are the (p, v) pairs, whose edges are the mesh
    edges copied into every ball that contains both ends, and one call to ``connected_components``.

    Args:
        center, sample: (P,) the candidate pairs, sorted by ``center``.

    Returns:
        (P,) bool.
    """
    n = surface.n_vertices
    edges, longest = _surface_graph(surface)
    node_p, node_v = _ball_nodes(surface.vertices, r0 + longest)
    # Each undirected edge once (u < w): the undirected component search does not need both directions.
    upper = scipy.sparse.csr_matrix(
        (np.ones(len(edges), dtype=np.int8), (edges.min(axis=1), edges.max(axis=1))), shape=(n, n)
    )
    upper.sum_duplicates()
    sample_node = sample if samples.face_index is None else surface.faces[samples.face_index[sample], 0]
    source, target, sample_slot, own = _link_ball_nodes(node_p, node_v, upper, center, sample_node)

    indptr = np.concatenate([[0], np.cumsum(np.bincount(source, minlength=len(node_p)))])
    graph = scipy.sparse.csr_matrix((np.ones(len(source), dtype=np.int8), target, indptr), shape=(len(node_p),) * 2)
    _, label = connected_components(graph, directed=False)
    reached = sample_slot >= 0
    reached[reached] = label[sample_slot[reached]] == label[own[center[reached]]]
    return reached


def _ball_nodes(points: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray]:
    """Nodes (p, v) of the sheet graph: every vertex v within ``reach`` of p, including (p, p), grouped by p.

    Returns:
        (node_p, node_v), each (Q,) int64, sorted by ``node_p`` (stable).
    """
    n = points.shape[0]
    near = cKDTree(points).query_pairs(reach, output_type="ndarray")
    node_p = np.concatenate([near[:, 0], near[:, 1], np.arange(n)])
    node_v = np.concatenate([near[:, 1], near[:, 0], np.arange(n)])
    order = np.argsort(node_p, kind="stable")
    return node_p[order], node_v[order]


def _link_ball_nodes(node_p, node_v, upper, center, sample_node):
    """Edges between the nodes of every ball, and the node of each candidate pair and of each ball centre.

    Node look-ups go through a dense (vertex block × N) table of node ids, filled one block of centre
    vertices at a time (so it never holds more than ``_TABLE_ENTRIES`` entries).

    Args:
        node_p, node_v: from :func:`_ball_nodes`.
        upper: (N, N) CSR graph with every undirected surface edge once.
        center, sample_node: (P,) the candidate pairs' centre vertex and the graph vertex of their sample.

    Returns:
        (source, target, sample_slot, own): the sheet graph's edges as node ids (source sorted), the node
        (p, sample_node) of each pair (-1 when outside p's ball) and the node (p, p) of each vertex.
    """
    n = upper.shape[0]
    node_start = np.searchsorted(node_p, np.arange(n + 1))
    pair_start = np.searchsorted(center, np.arange(n + 1))
    block = max(1, min(n, _TABLE_ENTRIES // max(n, 1)))
    table = np.full((block, n), -1, dtype=np.int64)
    sources, targets = [], []
    sample_slot = np.empty(len(center), dtype=np.int64)
    own = np.empty(n, dtype=np.int64)
    degrees = np.diff(upper.indptr)
    for first in range(0, n, block):
        last = min(n, first + block)
        a, b = node_start[first], node_start[last]
        ids = np.arange(a, b)
        table[node_p[a:b] - first, node_v[a:b]] = ids
        # Edges (p, u) - (p, w) for every graph edge u -> w whose both ends are in p's ball.
        u = node_v[a:b]
        degree = degrees[u]
        source = np.repeat(ids, degree)
        offset = np.arange(len(source)) - np.repeat(np.cumsum(degree) - degree, degree)
        neighbour = upper.indices[np.repeat(upper.indptr[u], degree) + offset]
        target = table[node_p[source] - first, neighbour]
        present = target >= 0
        sources.append(source[present])
        targets.append(target[present])
        c, d = pair_start[first], pair_start[last]
        sample_slot[c:d] = table[center[c:d] - first, sample_node[c:d]]
        own[first:last] = table[np.arange(last - first), np.arange(first, last)]
        table[node_p[a:b] - first, node_v[a:b]] = -1
    return np.concatenate(sources), np.concatenate(targets), sample_slot, own
