"""Refining a prediction by its consistency: neighbours map to neighbours, and share a part.

A correspondence network scores every pair (vertex ``i`` of a shape, vertex ``j`` of the template) on its
own. A true map sends the neighbours of ``i`` near ``j``, so the refined score of ``(i, j)`` asks each
neighbour for its agreement:

    S(i, j) = log(P(i, j) + ε) + Σ_{k ∈ ring(i), k ≠ i} log(Σ_{l ∈ ring(j)} P(k, l) + ε),

where ``P`` (N × M) holds the predicted probabilities, ``ring(v)`` the vertices at most ``rings`` mesh edges
from ``v`` (itself included), and the refined scores are the softmax of ``S`` over ``j``: the network's own
belief times, for every neighbour ``k``, the probability ``k`` gives to landing near ``j`` (one step of
belief propagation on the mesh, with "neighbours map within a ring of each other" as the pairwise term).
A product asks every neighbour, where an average (``A · P · Aᵀ``, the first form of this module) lets a few
sure ones outvote the rest: on 20 scans of 2 unseen generated people it turns 96.5 % exact into 99.4 % over
one ring and 99.7 % over two, where the average gave 98.9 and 98.5 % (``benchmarks/experiments/refinement.py``). ``ε`` keeps one disagreeing neighbour (across a seam the
network got wrong) from vetoing a vertex. A whole region mapped to the wrong place (a left leg on the
right one) agrees with itself and stays as it is: that is the work of the global step that follows
(:mod:`zernet.inference.spectral_refine`).

The step can be repeated (``passes``): each pass takes the last one's refined scores as its probabilities, so
agreement travels further than one ring radius while each vertex still asks only its own ring. On a real
person never trained on (FAUST person 6, the shipped correspondence recipe) one pass over 3 rings gave 86.3 %
exact, over 6 rings 89.6 %, two passes over 3 rings 93.3 % and over 4 rings 94.8 %
(``eval.refine_passes``; the ring count and the passes are chosen together on the validation split). The rings count mesh edges, so they follow the surface and never
bridge a fold (fingers, armpits). The best radius is chosen on validation shapes (``eval.refine_rings``).

Cost: two sparse-dense products with as many non-zeros per row as a ring holds (7, 19, 37 vertices for 1,
2, 3 rings of a regular mesh) and three element-wise passes over the (N, M) scores (1.7 s for a 6,890-vertex
scan at one CPU thread over one ring, 2.3 s over two: about 1.5 times the average's), computed with torch on
the device the probabilities are on (the run's device during evaluation: no scipy on the host while the GPU
waits). The rings of a mesh are built once per (faces, rings, device) and kept (:func:`ring_tensor`): every
shape of a correspondence by vertex index shares the template's faces.

A segmentation is refined on the shape alone (:func:`refine_segmentation`), by the plain average of the
rings and only where the network is unsure: a vertex whose predicted part has probability below
:data:`SEGMENTATION_CONFIDENCE` takes the average of its rings. The unsure vertices are where a patch saw
something the training shapes did not show (the rim of a partial scan, a noisy or bridged point cloud); the
sure ones are mostly right, and averaging them too only moves the boundaries between parts (measured in
:data:`SEGMENTATION_CONFIDENCE`).
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
    "ring_reach",
    "ring_average",
    "ring_tensor",
    "refine_correspondence",
    "refine_segmentation",
    "AGREEMENT_FLOOR",
    "SEGMENTATION_CONFIDENCE",
]

#: Segmentation: vertices predicted with at least this probability keep their answer. Chosen on 10 generated
#: validation bodies (another seed than the benchmark's) in six forms, with a model trained on the mixed
#: forms of ``benchmarks/experiments/scans.py``; accuracy raw / averaged everywhere / below 0.9 only, 2 rings: original
#: 99.15 / 98.93 / 99.23 %, remeshed 98.28 / 98.23 / 98.37, decimated 98.39 / 97.72 / 98.35, uniform cloud
#: 95.20 / 96.49 / 96.21, noisy half cloud 90.47 / 93.34 / 92.79, partial 93.58 / 95.91 / 95.36.
SEGMENTATION_CONFIDENCE = 0.9


def ring_reach(faces: np.ndarray, n_vertices: int, rings: int) -> sp.csr_matrix:
    """(n_vertices, n_vertices) symmetric 0/1 float32 CSR matrix: entry ``(i, j)`` is 1 when vertex ``j`` is
    at most ``rings`` mesh edges from vertex ``i`` (itself included; rings 0: the identity)."""
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
    return reach.tocsr()


def ring_average(faces: np.ndarray, n_vertices: int, rings: int) -> sp.csr_matrix:
    """(n_vertices, n_vertices) row-stochastic float32 CSR matrix: row ``i`` averages, with equal weights,
    vertex ``i`` and every vertex at most ``rings`` mesh edges away (:func:`ring_reach`, normalised). A
    vertex no face references averages only itself."""
    reach = ring_reach(faces, n_vertices, rings)
    count = np.asarray(reach.sum(axis=1), dtype=np.float32).ravel()
    return (sp.diags(1.0 / count).astype(np.float32) @ reach).tocsr()


def ring_tensor(faces: np.ndarray, n_vertices: int, rings: int, device, average: bool) -> torch.Tensor:
    """:func:`ring_average` (``average``) or :func:`ring_reach` as a torch float32 CSR matrix on ``device``,
    built once per (faces, rings, kind, device) and kept (the last :data:`_KEPT` of them)."""
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    key = (
        hashlib.sha1(faces.tobytes()).hexdigest(),
        faces.shape,
        int(n_vertices),
        int(rings),
        bool(average),
        str(torch.device(device)),
    )
    if key not in _RINGS:
        matrix = (ring_average if average else ring_reach)(faces, n_vertices, rings)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # "sparse CSR support is in beta"
            tensor = torch.sparse_csr_tensor(
                torch.from_numpy(matrix.indptr.astype(np.int64)),
                torch.from_numpy(matrix.indices.astype(np.int64)),
                torch.from_numpy(matrix.data),
                size=matrix.shape,
            )
        _RINGS[key] = tensor.to(device)
        while len(_RINGS) > _KEPT:
            _RINGS.pop(next(iter(_RINGS)))
    return _RINGS[key]


#: Ring matrices kept by :func:`ring_tensor` (a data set has one template: a few per rings candidate).
_KEPT = 8
_RINGS: dict[tuple, torch.Tensor] = {}

#: ``ε`` of the module docstring, in units of the uniform probability ``1 / M``: a neighbour that gives a
#: ring less than this counts as this. On the unseen validation people of ``benchmarks/experiments/few_people.py`` (the
#: shipped FAUST recipe's model), 2 / 7 / 20 / 60 gave 99.39 / 99.38 / 99.37 / 99.36 % exact after one ring
#: and 99.74 / 99.74 / 99.72 / 99.72 % after two: it hardly matters below 20; 7 (1e-3 at 6,890 vertices)
#: lets a neighbour that gives a ring a thousandth of its mass still count as a weak "no", not a veto.
AGREEMENT_FLOOR = 7.0


def refine_correspondence(
    probabilities, shape_faces: np.ndarray, template_faces: np.ndarray, rings: int, passes: int = 1
):
    """The probabilities refined by the agreement of each vertex's ``rings``-ring, ``passes`` times (module
    docstring).

    Args:
        probabilities: (N, M) predicted probabilities: row ``i`` scores the M template vertices for vertex
            ``i`` of the shape. A torch tensor is refined on its device; a numpy array on the CPU.
        shape_faces: (F, 3) faces of the shape (N vertices).
        template_faces: (F', 3) faces of the template (M vertices). With correspondence by vertex index
            (FAUST, generated bodies) every shape has the template's connectivity.
        rings: the neighbourhood radius in mesh edges; 0 returns the probabilities unchanged.
        passes: how many times the step is applied, each to the last one's scores (>= 1).

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
    if passes < 1:
        raise ValueError(f"passes must be >= 1, got {passes}")
    if rings == 0:
        return scores.cpu().numpy() if as_numpy else scores
    n, m = scores.shape
    floor = AGREEMENT_FLOOR / m
    shape_rings = ring_tensor(shape_faces, n, rings, scores.device, average=False)
    template_rings = ring_tensor(template_faces, m, rings, scores.device, average=False)
    for _ in range(passes):
        # mass[k, j]: what vertex k gives the ring of j (the template's rings are symmetric: R·Pᵀ = (P·R)ᵀ).
        agreement = (template_rings @ scores.T.contiguous()).T.add_(floor).log_()
        # Every neighbour's agreement, without the vertex's own (it speaks through its probability).
        support = (shape_rings @ agreement).sub_(agreement)
        del agreement
        scores = torch.softmax(scores.add(floor).log_().add_(support), dim=1)
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
        averaged = ring_tensor(faces, scores.shape[0], rings, scores.device, average=True) @ scores
        unsure = scores.max(dim=1).values < confidence
        scores = torch.where(unsure[:, None], averaged, scores).contiguous()
    return scores.cpu().numpy() if as_numpy else scores
