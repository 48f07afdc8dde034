"""Refining a prediction by its consistency: neighbours map to neighbours, and share a part.

A correspondence network scores every pair (vertex ``i`` of a shape, vertex ``j`` of the template) on its
own. A true map sends the neighbours of ``i`` near the neighbours of ``j``, so the refined score of
``(i, j)`` is the predicted probability averaged over both neighbourhoods:

    Q = A_shape · P · A_templateᵀ,

where ``P`` (N × M) holds the predicted probabilities and ``A`` is a mesh's ring average: row ``i`` averages,
with equal weights, the vertices at most ``rings`` edges from vertex ``i``. A vertex whose own scores are
unsure or wrong takes the answer its neighbourhood agrees on; a whole region mapped to the wrong place (a
left leg on the right one) stays as it is: that is the work of the global step that follows
(:mod:`zernet.training.spectral_refine`). The rings count mesh edges, so they follow the surface and never
bridge a fold (fingers, armpits). The best radius grows with the mesh resolution and is chosen on validation
shapes (``eval.refine_rings``). Averaging once over ``r`` rings is not the same as averaging ``r`` times over
one ring: repeated averaging weights each vertex by how its rings overlap its neighbours', which on an
irregular mesh moves the maximum off a perfect map.

Cost: two sparse-dense products with as many non-zeros per row as a ring holds (7, 19, 37 vertices for 1,
2, 3 rings of a regular mesh), computed with torch on the device the probabilities are on (the run's device
during evaluation: no scipy on the host while the GPU waits). The ring averages of a mesh are built once per
(faces, rings, device) and kept (:func:`ring_average_tensor`): every shape of a correspondence by vertex
index shares the template's faces.

A segmentation is refined the same way on the shape alone (:func:`refine_segmentation`), but only where the
network is unsure: a vertex whose predicted part has probability below :data:`SEGMENTATION_CONFIDENCE` takes
the average of its rings. The unsure vertices are where a patch saw something the training shapes did not
show (the rim of a partial scan, a noisy or bridged point cloud); the sure ones are mostly right, and
averaging them too only moves the boundaries between parts (measured in :data:`SEGMENTATION_CONFIDENCE`).
A point cloud is averaged over the rings of its triangulation through its own points
(:func:`zernet.geometry.cloud_mesh.mesh_from_cloud`), which is what its patches were built on.
"""

from __future__ import annotations

import hashlib
import warnings

import numpy as np
import scipy.sparse as sp
import torch

__all__ = [
    "ring_average",
    "ring_average_tensor",
    "refine_correspondence",
    "refine_segmentation",
    "SEGMENTATION_CONFIDENCE",
]

#: Segmentation: vertices predicted with at least this probability keep their answer. Chosen on 10 generated
#: validation bodies (another seed than the benchmark's) in six forms, with a model trained on the mixed
#: forms of ``benchmarks/scans.py``; accuracy raw / averaged everywhere / below 0.9 only, 2 rings: original
#: 99.15 / 98.93 / 99.23 %, remeshed 98.28 / 98.23 / 98.37, decimated 98.39 / 97.72 / 98.35, uniform cloud
#: 95.20 / 96.49 / 96.21, noisy half cloud 90.47 / 93.34 / 92.79, partial 93.58 / 95.91 / 95.36.
SEGMENTATION_CONFIDENCE = 0.9


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


def ring_average_tensor(faces: np.ndarray, n_vertices: int, rings: int, device) -> torch.Tensor:
    """:func:`ring_average` as a torch float32 CSR matrix on ``device``, built once per (faces, rings,
    device) and kept (the last :data:`_KEPT` of them)."""
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    key = (
        hashlib.sha1(faces.tobytes()).hexdigest(),
        faces.shape,
        int(n_vertices),
        int(rings),
        str(torch.device(device)),
    )
    if key not in _RING_AVERAGES:
        matrix = ring_average(faces, n_vertices, rings)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # "sparse CSR support is in beta"
            tensor = torch.sparse_csr_tensor(
                torch.from_numpy(matrix.indptr.astype(np.int64)),
                torch.from_numpy(matrix.indices.astype(np.int64)),
                torch.from_numpy(matrix.data),
                size=matrix.shape,
            )
        _RING_AVERAGES[key] = tensor.to(device)
        while len(_RING_AVERAGES) > _KEPT:
            _RING_AVERAGES.pop(next(iter(_RING_AVERAGES)))
    return _RING_AVERAGES[key]


#: Ring averages kept by :func:`ring_average_tensor` (a data set has one template: one per rings candidate).
_KEPT = 8
_RING_AVERAGES: dict[tuple, torch.Tensor] = {}


def refine_correspondence(probabilities, shape_faces: np.ndarray, template_faces: np.ndarray, rings: int):
    """The probabilities averaged over the ``rings``-ring of the shape's vertex and of the template's.

    Args:
        probabilities: (N, M) predicted probabilities: row ``i`` scores the M template vertices for vertex
            ``i`` of the shape. A torch tensor is refined on its device; a numpy array on the CPU.
        shape_faces: (F, 3) faces of the shape (N vertices).
        template_faces: (F', 3) faces of the template (M vertices). With correspondence by vertex index
            (FAUST, generated bodies) every shape has the template's connectivity.
        rings: the neighbourhood radius in mesh edges; 0 returns the probabilities unchanged.

    Returns:
        (N, M) float32 scores, each row a distribution (its maximum is the refined correspondence), of the
        input's kind: a tensor on its device, or a numpy array.
    """
    as_numpy = not isinstance(probabilities, torch.Tensor)
    scores = torch.as_tensor(
        np.asarray(probabilities, dtype=np.float32) if as_numpy else probabilities, dtype=torch.float32
    )
    if scores.dim() != 2:
        raise ValueError(f"probabilities must have shape (N, M), got {tuple(scores.shape)}")
    if rings < 0:
        raise ValueError(f"rings must be >= 0, got {rings}")
    if rings > 0:
        n, m = scores.shape
        shape_average = ring_average_tensor(shape_faces, n, rings, scores.device)
        template_average = ring_average_tensor(template_faces, m, rings, scores.device)
        scores = shape_average @ scores  # A·P
        scores = (template_average @ scores.T.contiguous()).T  # Q·Aᵀ = (A·Qᵀ)ᵀ: the sparse factor on the left
        scores = (scores / scores.sum(dim=1, keepdim=True)).contiguous()  # Aᵀ is not stochastic
    return scores.cpu().numpy() if as_numpy else scores


def refine_segmentation(probabilities, faces: np.ndarray, rings: int, confidence: float = SEGMENTATION_CONFIDENCE):
    """The probabilities of the vertices the network is unsure of, averaged over their ``rings``-ring.

    Args:
        probabilities: (N, C) predicted class probabilities of a shape's N vertices. A torch tensor is
            refined on its device; a numpy array on the CPU.
        faces: (F, 3) faces of the shape (a point cloud: of its triangulation through its points).
        rings: the neighbourhood radius in mesh edges; 0 returns the probabilities unchanged.
        confidence: rows whose largest probability is at least this stay as they are.

    Returns:
        (N, C) float32 probabilities of the input's kind (a tensor on its device, or a numpy array).
    """
    as_numpy = not isinstance(probabilities, torch.Tensor)
    scores = torch.as_tensor(
        np.asarray(probabilities, dtype=np.float32) if as_numpy else probabilities, dtype=torch.float32
    )
    if scores.dim() != 2:
        raise ValueError(f"probabilities must have shape (N, C), got {tuple(scores.shape)}")
    if rings < 0:
        raise ValueError(f"rings must be >= 0, got {rings}")
    if rings > 0:
        averaged = ring_average_tensor(faces, scores.shape[0], rings, scores.device) @ scores
        unsure = scores.max(dim=1).values < confidence
        scores = torch.where(unsure[:, None], averaged, scores).contiguous()
    return scores.cpu().numpy() if as_numpy else scores
