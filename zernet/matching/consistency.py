"""Global consistency of a point map: the vertices whose map does not come back, or does not keep their
distances to the rest of the body, are mapped again by their geodesic distances to the vertices that pass.

The template model (:mod:`zernet.matching.template`) reads each vertex on its own; on a pose it never saw
(arms raised overhead), a whole limb can be read as another part, and its vertices go to the wrong limb or
the torso, while the rest of the body is right. :func:`repair_map`:

1. **Round trip**: a source vertex whose cycle confidence (:func:`zernet.matching.fmap.cycle_confidence`:
   source -> target -> source) is below :data:`TRUST_THRESHOLD` is untrusted; the others are trusted.
2. **Landmarks**: :data:`LANDMARKS` trusted vertices spread over the source (farthest-point sampling), and
   their images on the target.
3. **Distances**: on each surface, the shortest-path distance along its edges (a mesh) or its
   nearest-neighbour graph (a point cloud) from every vertex to every landmark (:func:`landmark_distances`),
   compared as square roots, so that the far landmarks, whose distances two different people stretch most,
   count less.
4. **Distortion**: a limb swapped both ways survives the round trip, but its vertices' distances to the
   landmarks do not match their images' distances to the landmarks' images. A trusted vertex whose mismatch
   (the median over the landmarks, so that a few swapped landmarks do not make every vertex look distorted)
   is more than :data:`DISTORTION_FACTOR` times the trusted vertices' median is untrusted too, and the
   landmarks are drawn again from the vertices left.
5. **Repair**: every untrusted source vertex goes to the target vertex whose distances to the landmarks'
   images are nearest its own distances to the landmarks. A point's distances to landmarks on both sides of
   the body tell the left arm from the right and the arm from the torso, whatever the template model read
   there.

It assumes what any intrinsic method does: the two surfaces are nearly isometric at the scale of a body's
parts (two people, in any pose) and in the same units (the matcher scales both). Measured on real FAUST
scans of different people (people 0-7, 4 development pairs per form; mean error x100 / sqrt(area)): the
template map 7.01 remeshed, 10.00 anisotropic, 4.46 as a noisy cloud; the round trip alone (steps 1-3, 5)
2.75, 4.02, 3.12; with the distortion check 2.48, 2.79, 3.00, in under a second per pair. ZoomOut started
from the template map (the functional-map repair: plain, weighted by the confidence, or with the template
positions as features) gave 6.0-11.6 on 3 of the remeshed pairs whose template map scores 8.61, and ZoomOut
after the repair 2.9-7.0 against the repair's 2.75 (and 14 s more per pair): not used.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse
import scipy.sparse.csgraph
from scipy.spatial import cKDTree

from zernet.geometry import Surface
from zernet.operators.spectral import nearest_rows

__all__ = [
    "TRUST_THRESHOLD",
    "LANDMARKS",
    "DISTORTION_FACTOR",
    "CLOUD_NEIGHBOURS",
    "edge_graph",
    "landmark_distances",
    "farthest_points",
    "repair_map",
]

#: Cycle confidence at and above which a vertex's map is kept and may serve as a landmark (a round trip
#: within about 0.8 of :data:`zernet.matching.match.CONFIDENCE_SCALE`).
TRUST_THRESHOLD = 0.5

#: Landmarks the untrusted vertices are located by (64 and 128 gave the same errors on real scans).
LANDMARKS = 64

#: A trusted vertex whose distances to the landmarks mismatch its image's by more than this many times the
#: trusted vertices' median mismatch is untrusted (3 against 2 and 4: 2.48 / 2.79 / 3.00 against
#: 2.49 / 2.75 / 3.19 and 2.50 / 3.02 / 2.99 on the development pairs above).
DISTORTION_FACTOR = 3.0

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
    distortion_factor: float = DISTORTION_FACTOR,
) -> tuple[np.ndarray, int]:
    """(the map source -> target with its untrusted vertices mapped again, how many were) (module docstring).

    Args:
        source, target: the two surfaces in the same units (meshes or point clouds).
        vertex_map: (N_source,) target vertex of each source vertex.
        confidence: (N_source,) in [0, 1], the round trip's (:func:`zernet.matching.fmap.cycle_confidence`).
        threshold: confidence below which a vertex is untrusted.
        landmarks: how many trusted vertices locate the others.
        distortion_factor: mismatch of distances, in trusted vertices' medians, above which a vertex is
            untrusted (``inf``: the round trip alone decides).

    The map is returned as it is when no vertex is untrusted, or when fewer trusted vertices than
    ``landmarks`` remain (nothing to locate them by).
    """
    vertex_map = np.asarray(vertex_map, dtype=np.int64)
    untrusted = np.asarray(confidence) < threshold
    if (~untrusted).sum() < landmarks:
        return vertex_map, 0
    on_source, on_target = _landmark_views(source, target, vertex_map, ~untrusted, landmarks)
    mismatch = np.median(np.abs(on_source - on_target[vertex_map]), axis=1)
    distorted = ~untrusted & (mismatch > distortion_factor * np.median(mismatch[~untrusted]))
    if distorted.any():
        untrusted |= distorted
        if (~untrusted).sum() < landmarks:
            return vertex_map, 0
        on_source, on_target = _landmark_views(source, target, vertex_map, ~untrusted, landmarks)
    if not untrusted.any():
        return vertex_map, 0
    repaired = vertex_map.copy()
    repaired[untrusted] = nearest_rows(on_source[untrusted], on_target)
    return repaired, int(untrusted.sum())


def _landmark_views(
    source: Surface, target: Surface, vertex_map: np.ndarray, trusted: np.ndarray, landmarks: int
) -> tuple[np.ndarray, np.ndarray]:
    """(square roots of the source's distances to landmarks among the ``trusted`` vertices (N_source, L), and of
    the target's distances to their images (N_target, L))."""
    chosen = farthest_points(np.asarray(source.vertices), np.flatnonzero(trusted), landmarks)
    return np.sqrt(landmark_distances(source, chosen)), np.sqrt(landmark_distances(target, vertex_map[chosen]))
