"""The template of a correspondence run, as a graph: which template vertices lie near which.

Two steps read it: the global refinement (:mod:`zernet.inference.spectral_refine`: the candidates near a
spectral map's answer) and the geodesic soft labels of the loss (``train.label_radius``: a vertex's target is
spread over the template vertices near its true one, so that answering a neighbour of the true vertex costs
less than answering the other knee). Distances run along the mesh edges (Dijkstra): at most a few percent
longer than the geodesic on a body mesh, and exact enough to bound a neighbourhood.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.csgraph
import torch

__all__ = ["edge_graph", "edge_neighbourhoods", "padded_neighbourhoods", "geodesic_soft_labels"]

#: Sources per Dijkstra call: bounds the dense (sources, M) distance block in memory.
_CHUNK = 512


def edge_graph(vertices: np.ndarray, faces: np.ndarray) -> sp.csr_matrix:
    """(M, M) symmetric sparse matrix of the mesh's edge lengths."""
    vertices, faces = np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64)
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    lengths = np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1)
    n = len(vertices)
    graph = sp.coo_matrix((lengths, (edges[:, 0], edges[:, 1])), shape=(n, n)).tocsr()
    return graph.maximum(graph.T).tocsr()


def edge_neighbourhoods(graph: sp.csr_matrix, limit: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """For each vertex, (indices, distances) of the vertices within ``limit`` along the edges, itself
    included (distance 0)."""
    n = graph.shape[0]
    found = []
    for start in range(0, n, _CHUNK):
        sources = np.arange(start, min(n, start + _CHUNK))
        distances = scipy.sparse.csgraph.dijkstra(graph, indices=sources, limit=limit)
        for row in distances:
            near = np.flatnonzero(np.isfinite(row))
            found.append((near, row[near]))
    return found


def padded_neighbourhoods(found: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """The lists of :func:`edge_neighbourhoods` as one (M, K) table of indices (K the longest list; a shorter
    row is padded with its own vertex) and one (M, K) table of distances (``inf`` in the padding)."""
    width = max(len(near) for near, _ in found)
    indices = np.repeat(np.arange(len(found))[:, None], width, axis=1)
    distances = np.full((len(found), width), np.inf)
    for i, (near, dist) in enumerate(found):
        indices[i, : len(near)] = near
        distances[i, : len(near)] = dist
    return indices, distances


def geodesic_soft_labels(
    vertices: np.ndarray, faces: np.ndarray, radius: float, diameter: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """The soft target of each template vertex: a Gaussian of the edge distance with σ = ``radius`` / 2,
    cut at ``radius`` (both in units of ``diameter``), normalised to sum to 1.

    Returns ``indices`` (M, K) int64 and ``weights`` (M, K) float32: the target of a vertex whose true
    template vertex is ``t`` puts ``weights[t, k]`` on ``indices[t, k]``; padding has weight 0. The true
    vertex always has the largest weight, so the argmax of the target is the hard label.
    """
    limit = float(radius) * float(diameter)
    indices, distances = padded_neighbourhoods(edge_neighbourhoods(edge_graph(vertices, faces), limit))
    sigma = limit / 2.0
    weights = np.exp(-0.5 * (distances / sigma) ** 2)  # exp(-inf) = 0 in the padding
    weights /= weights.sum(axis=1, keepdims=True)
    return torch.from_numpy(indices), torch.from_numpy(weights.astype(np.float32))
