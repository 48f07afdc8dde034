"""Global consistency of a point map: the vertices whose map does not come back are mapped again, by their
geodesic distances to the vertices whose map does.

The template model (:mod:`zernet.matching.template`) reads each vertex on its own; on a pose it never saw
(arms raised overhead), a whole limb can be read as another part, and its vertices go to the wrong limb or
the torso, while the rest of the body is right. Such a vertex does not survive the round trip source ->
target -> source (its cycle confidence, :func:`zernet.matching.fmap.cycle_confidence`, is low), and the
repair uses only that:

1. **Trusted vertices**: source vertices whose confidence is at least :data:`TRUST_THRESHOLD`.
2. **Landmarks**: :data:`LANDMARKS` trusted vertices spread over the source (farthest-point sampling), and
   their images on the target.
3. **Distances**: on each surface, the shortest-path distance along its edges (a mesh) or its
   nearest-neighbour graph (a point cloud) from every vertex to every landmark
   (:func:`landmark_distances`).
4. **Repair**: every untrusted source vertex goes to the target vertex whose distances to the landmarks' images
   are nearest its own distances to the landmarks (square roots of the distances, so that the far
   landmarks, whose distances two different people stretch most, count less). A point's distances to
   landmarks on both sides of the body tell the left arm from the right and the arm from the torso, whatever
   the template model read there.

It assumes what any intrinsic method does: the two surfaces are nearly isometric at the scale of a body's
parts (two people, in any pose) and in the same units (the matcher scales both). On real FAUST scans of
different people (remeshed, 4 pairs) it took the mean error from 7.01 to 2.75 in 0.3-0.4 s per pair, while
ZoomOut started from the template map (the functional-map repair) gave 9.5, and ZoomOut after the repair
2.9-6.9 (``benchmarks/experiments/results/matching_real.md``).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse
import scipy.sparse.csgraph
from scipy.spatial import cKDTree

from zernet.geometry import Surface
from zernet.operators.spectral import nearest_rows

__all__ = ["TRUST_THRESHOLD", "LANDMARKS", "CLOUD_NEIGHBOURS", "edge_graph", "landmark_distances", "repair_map"]

#: Cycle confidence at and above which a vertex's map is kept and may serve as a landmark (a round trip
#: within about 0.8 of :data:`zernet.matching.match.CONFIDENCE_SCALE`).
TRUST_THRESHOLD = 0.5

#: Landmarks the untrusted vertices are located by (64 and 128 gave the same errors on real scans).
LANDMARKS = 64

#: Neighbours each point of a cloud is joined to in its distance graph.
CLOUD_NEIGHBOURS = 8


def edge_graph(surface: Surface) -> scipy.sparse.csr_matrix:
    """(N, N) symmetric sparse matrix of edge lengths: a mesh's edges, or for a point cloud (no faces) each
    point joined to its :data:`CLOUD_NEIGHBOURS` nearest points."""
    vertices = np.asarray(surface.vertices, dtype=np.float64)
    faces = surface.faces
    if faces is not None and len(faces):
        faces = np.asarray(faces, dtype=np.int64)
        edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    else:
        k = min(CLOUD_NEIGHBOURS, len(vertices) - 1)
        _, nearest = cKDTree(vertices).query(vertices, k=k + 1)
        edges = np.stack([np.repeat(np.arange(len(vertices)), k), np.asarray(nearest)[:, 1:].ravel()], axis=1)
    lengths = np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1)
    n = len(vertices)
    graph = scipy.sparse.coo_matrix((lengths, (edges[:, 0], edges[:, 1])), shape=(n, n)).tocsr()
    return graph.maximum(graph.T)


def landmark_distances(surface: Surface, landmarks: np.ndarray) -> np.ndarray:
    """(N, L) shortest-path distance along :func:`edge_graph` from every vertex to each landmark. A vertex in
    another piece than a landmark (a one-sided scan in pieces) is given twice the largest finite distance:
    far, as it is on the whole body."""
    distances = scipy.sparse.csgraph.dijkstra(edge_graph(surface), indices=np.asarray(landmarks)).T
    finite = np.isfinite(distances)
    distances[~finite] = 2.0 * distances[finite].max(initial=1.0)
    return distances


def farthest_points(vertices: np.ndarray, candidates: np.ndarray, n: int) -> np.ndarray:
    """``n`` of ``candidates`` (vertex indices) spread over the shape: farthest-point sampling in space, from
    the first candidate."""
    chosen = [int(candidates[0])]
    distance = np.linalg.norm(vertices[candidates] - vertices[chosen[0]], axis=1)
    for _ in range(min(n, len(candidates)) - 1):
        index = int(np.argmax(distance))
        chosen.append(int(candidates[index]))
        distance = np.minimum(distance, np.linalg.norm(vertices[candidates] - vertices[candidates[index]], axis=1))
    return np.asarray(chosen, dtype=np.int64)


def repair_map(
    source: Surface,
    target: Surface,
    vertex_map: np.ndarray,
    confidence: np.ndarray,
    threshold: float = TRUST_THRESHOLD,
    landmarks: int = LANDMARKS,
) -> tuple[np.ndarray, int]:
    """(the map source -> target with its untrusted vertices mapped again, how many were) (module docstring).

    Args:
        source, target: the two surfaces in the same units (meshes or point clouds).
        vertex_map: (N_source,) target vertex of each source vertex.
        confidence: (N_source,) in [0, 1], the round trip's (:func:`zernet.matching.fmap.cycle_confidence`).
        threshold: confidence below which a vertex is mapped again.
        landmarks: how many trusted vertices locate the others.

    The map is returned as it is when no vertex is untrusted, or when fewer trusted vertices than
    ``landmarks`` remain (nothing to locate them by).
    """
    vertex_map = np.asarray(vertex_map, dtype=np.int64)
    confidence = np.asarray(confidence)
    trusted = np.flatnonzero(confidence >= threshold)
    untrusted = np.flatnonzero(confidence < threshold)
    if len(untrusted) == 0 or len(trusted) < landmarks:
        return vertex_map, 0
    chosen = farthest_points(np.asarray(source.vertices), trusted, landmarks)
    # Square roots: the error of a distance between two people grows with its length.
    on_source = np.sqrt(landmark_distances(source, chosen))
    on_target = np.sqrt(landmark_distances(target, vertex_map[chosen]))
    repaired = vertex_map.copy()
    repaired[untrusted] = nearest_rows(on_source[untrusted], on_target)
    return repaired, len(untrusted)
