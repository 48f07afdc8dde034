"""Refining a predicted correspondence by its consistency: neighbours map to neighbours.

A correspondence network scores every pair (vertex ``i`` of a shape, vertex ``j`` of the template) on its
own. A true map sends the neighbours of ``i`` near the neighbours of ``j``, so the refined score of
``(i, j)`` is the predicted probability averaged over both neighbourhoods:

    Q = A_shape · P · A_templateᵀ,

where ``P`` (N × M) holds the predicted probabilities and ``A`` is a mesh's ring average: row ``i`` averages,
with equal weights, the vertices at most ``rings`` edges from vertex ``i``. A vertex whose own scores are
unsure or wrong takes the answer its neighbourhood agrees on; a whole region mapped to the wrong place (a
left leg on the right one) stays as it is. The rings count mesh edges, so they follow the surface and never
bridge a fold (fingers, armpits). The best radius grows with the mesh resolution and is chosen on validation
shapes (``eval.refine_rings``). Averaging once over ``r`` rings is not the same as averaging ``r`` times over
one ring: repeated averaging weights each vertex by how its rings overlap its neighbours', which on an
irregular mesh moves the maximum off a perfect map.

Cost: two sparse-dense products with as many non-zeros per row as a ring holds (7, 19, 37 vertices for 1,
2, 3 rings of a regular mesh): about 0.2 s for 6,890 × 6,890 scores and one ring.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

__all__ = ["ring_average", "refine_correspondence"]


def ring_average(faces: np.ndarray, n_vertices: int, rings: int) -> sp.csr_matrix:
    """(n_vertices, n_vertices) row-stochastic float32 CSR matrix: row ``i`` averages, with equal weights,
    vertex ``i`` and every vertex at most ``rings`` mesh edges away (rings 0: the identity). A vertex no
    face references averages only itself."""
    faces = np.asarray(faces, dtype=np.int64)
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces must have shape (F, 3), got {faces.shape}")
    if faces.size and (faces.min() < 0 or faces.max() >= n_vertices):
        raise ValueError(f"faces index vertices outside [0, {n_vertices})")
    if rings < 0:
        raise ValueError(f"rings must be >= 0, got {rings}")
    rows = np.concatenate([faces[:, 0], faces[:, 1], faces[:, 2]])
    cols = np.concatenate([faces[:, 1], faces[:, 2], faces[:, 0]])
    one_ring = sp.coo_matrix((np.ones(len(rows), dtype=np.float32), (rows, cols)), shape=(n_vertices, n_vertices))
    one_ring = (one_ring + one_ring.T + sp.identity(n_vertices, dtype=np.float32, format="csr")).tocsr()
    reach = sp.identity(n_vertices, dtype=np.float32, format="csr")
    for _ in range(rings):
        reach = reach @ one_ring
        reach.data[:] = 1.0  # only whether a vertex is reached counts, not by how many paths
    count = np.asarray(reach.sum(axis=1), dtype=np.float32).ravel()
    return (sp.diags(1.0 / count).astype(np.float32) @ reach).tocsr()


def refine_correspondence(probabilities: np.ndarray, shape_faces: np.ndarray, template_faces: np.ndarray,
                          rings: int) -> np.ndarray:
    """The probabilities averaged over the ``rings``-ring of the shape's vertex and of the template's.

    Args:
        probabilities: (N, M) predicted probabilities: row ``i`` scores the M template vertices for vertex
            ``i`` of the shape.
        shape_faces: (F, 3) faces of the shape (N vertices).
        template_faces: (F', 3) faces of the template (M vertices). With correspondence by vertex index
            (FAUST, generated bodies) every shape has the template's connectivity.
        rings: the neighbourhood radius in mesh edges; 0 returns the probabilities unchanged.

    Returns:
        (N, M) float32 scores, each row a distribution; its maximum is the refined correspondence.
    """
    probabilities = np.asarray(probabilities, dtype=np.float32)
    if probabilities.ndim != 2:
        raise ValueError(f"probabilities must have shape (N, M), got {probabilities.shape}")
    if rings < 0:
        raise ValueError(f"rings must be >= 0, got {rings}")
    if rings == 0:
        return probabilities
    n, m = probabilities.shape
    scores = ring_average(shape_faces, n, rings) @ probabilities
    scores = np.asarray((ring_average(template_faces, m, rings) @ scores.T).T)  # Q·Aᵀ = (A·Qᵀ)ᵀ: sparse left
    scores /= scores.sum(axis=1, keepdims=True)  # Aᵀ is not stochastic: keep each row a distribution
    return np.ascontiguousarray(scores)
