"""Array estimators for point clouds: nearest neighbours, PCA normals and their orientation, tangent-plane
Voronoi cell areas, quadric mean curvature, and the tangent-basis helpers they share.

Plain float64 arrays in, arrays out: :class:`zernet.geometry.surface.Surface` calls these for a surface
without faces and caches the results.

Public API: :data:`CLOUD_NEIGHBOURS`, :func:`nearest_neighbours`, :func:`pca_normals`, :func:`orient_normals`,
:func:`voronoi_cell_areas`, :func:`quadric_mean_curvature`, :func:`tangent_basis`, :func:`unit_rows`.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse
from scipy.sparse.csgraph import breadth_first_order, connected_components, minimum_spanning_tree
from scipy.spatial import cKDTree

__all__ = [
    "CLOUD_NEIGHBOURS",
    "nearest_neighbours",
    "pca_normals",
    "orient_normals",
    "voronoi_cell_areas",
    "quadric_mean_curvature",
    "tangent_basis",
    "unit_rows",
]

# Neighbourhood size for point-cloud normal, area and curvature estimation.
CLOUD_NEIGHBOURS = 16
# Number of directions used to integrate the tangent-plane Voronoi cell of a cloud point.
_VORONOI_DIRECTIONS = 128
# Points per chunk of the Voronoi integration: keeps the (chunk, directions, k) temporaries small.
_VORONOI_CHUNK = 2048


def unit_rows(vectors: np.ndarray) -> np.ndarray:
    """Rows scaled to unit length; zero rows stay zero."""
    vectors = np.asarray(vectors, dtype=np.float64)
    length = np.linalg.norm(vectors, axis=1, keepdims=True)
    return np.divide(vectors, length, out=np.zeros_like(vectors), where=length > 0)


def tangent_basis(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """An orthonormal tangent basis (t1, t2) per unit normal, each (N, 3), with (t1, t2, n) right-handed."""
    helper = np.where(np.abs(normals[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = unit_rows(np.cross(normals, helper))
    return t1, np.cross(normals, t1)


def nearest_neighbours(points: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Distances and indices of the ``k`` nearest other points of every point, each (N, k), nearest first."""
    distance, index = cKDTree(points).query(points, k=k + 1)
    return distance[:, 1:], index[:, 1:]  # column 0 is the point itself


def pca_normals(points: np.ndarray, neighbours: np.ndarray) -> np.ndarray:
    """Unoriented unit normals (N, 3): the direction of least variance of each point and its neighbours."""
    patch = np.concatenate([points[:, None, :], points[neighbours]], axis=1)
    centred = patch - patch.mean(axis=1, keepdims=True)
    covariance = np.einsum("nki,nkj->nij", centred, centred)
    _, vectors = np.linalg.eigh(covariance)
    return vectors[:, :, 0]


def orient_normals(points: np.ndarray, normals: np.ndarray, neighbours: np.ndarray) -> np.ndarray:
    """Flip normals (N, 3) to a consistent orientation (Hoppe et al. 1992); returns unit rows.

    Signs propagate along a minimum spanning tree of the neighbour graph that prefers nearly parallel
    normals and steps along the tangent planes (so it does not hop between the facing sheets of a thin part), starting in each connected part from the point with the largest x, whose normal is made to
    point towards +x (outward for a closed surface).
    """
    normals = np.array(normals, dtype=np.float64)
    n, k = neighbours.shape
    rows = np.repeat(np.arange(n), k)
    cols = neighbours.ravel()
    alignment = np.abs(np.einsum("ij,ij->i", normals[rows], normals[cols]))
    # Hoppe's weight (1 - |n_i·n_j|) plus how far the step leaves both tangent planes: across a thin part
    # or between touching limbs the normals are antiparallel (weight ~0 by Hoppe's term alone, so the tree
    # would cross there and flip the far sheet inward), but the step runs along the normals.
    offset = unit_rows(points[cols] - points[rows])
    leaving = np.abs(np.einsum("ij,ij->i", offset, normals[rows])) + np.abs(
        np.einsum("ij,ij->i", offset, normals[cols])
    )
    weight = 1.0 - alignment + leaving + 1e-9  # strictly positive: csgraph treats 0 as "no edge"
    graph = scipy.sparse.coo_matrix((weight, (rows, cols)), shape=(n, n)).tocsr()
    graph = graph.maximum(graph.T)
    tree = minimum_spanning_tree(graph)
    tree = tree + tree.T
    n_parts, part = connected_components(tree, directed=False)
    for component in range(n_parts):
        members = np.flatnonzero(part == component)
        root = members[np.argmax(points[members, 0])]
        if normals[root, 0] < 0:
            normals[root] = -normals[root]
        order, predecessor = breadth_first_order(tree, root, directed=False, return_predecessors=True)
        for node in order[1:]:
            if normals[node] @ normals[predecessor[node]] < 0:
                normals[node] = -normals[node]
    return unit_rows(normals)


def voronoi_cell_areas(
    points: np.ndarray, normals: np.ndarray, distance: np.ndarray, neighbours: np.ndarray
) -> np.ndarray:
    """Area (N,) of each point's Voronoi cell among its neighbours projected on its tangent plane.

    In directions without neighbours (the rim of an open cloud) the cell is clipped at half the distance
    to the farthest of the given neighbours.

    Args:
        points: (N, 3) positions; normals: (N, 3) unit normals.
        distance, neighbours: (N, k) from :func:`nearest_neighbours`.
    """
    t1, t2 = tangent_basis(normals)
    offsets = points[neighbours] - points[:, None, :]  # (N, k, 3)
    q = np.stack([np.einsum("nki,ni->nk", offsets, t1), np.einsum("nki,ni->nk", offsets, t2)], axis=-1)
    # Voronoi cell of the origin among the projected neighbours q_j: {x : x·q_j <= |q_j|²/2}. Along a
    # direction u its radius is min over q_j with u·q_j > 0 of (|q_j|²/2) / (u·q_j); area = ½∮ρ² dφ.
    phi = (np.arange(_VORONOI_DIRECTIONS) + 0.5) * (2 * np.pi / _VORONOI_DIRECTIONS)
    directions = np.stack([np.cos(phi), np.sin(phi)], axis=1)  # (D, 2)
    half_square = 0.5 * np.einsum("nkc,nkc->nk", q, q)  # (N, k)
    cap = 0.5 * distance[:, -1]  # clip where no neighbour bounds the cell (rim of an open cloud)
    areas = np.empty(len(points))
    for start in range(0, len(points), _VORONOI_CHUNK):
        chunk = slice(start, start + _VORONOI_CHUNK)
        projection = np.einsum("nkc,dc->ndk", q[chunk], directions)  # (n, D, k)
        with np.errstate(divide="ignore", invalid="ignore"):
            bound = np.where(projection > 0, half_square[chunk, None, :] / projection, np.inf)
        radius = np.minimum(bound.min(axis=2), cap[chunk, None])
        areas[chunk] = 0.5 * (radius**2).sum(axis=1) * (2 * np.pi / _VORONOI_DIRECTIONS)
    return areas


def quadric_mean_curvature(points: np.ndarray, normals: np.ndarray, neighbours: np.ndarray) -> np.ndarray:
    """Signed mean curvature (N,) from a least-squares quadric over each point's neighbours.

    ``h = a u² + b uv + c v² + d u + e v`` in the tangent frame of the normal; ``H = -(a + c)``.
    """
    t1, t2 = tangent_basis(normals)
    offsets = points[neighbours] - points[:, None, :]  # (N, k, 3)
    u = np.einsum("nki,ni->nk", offsets, t1)
    v = np.einsum("nki,ni->nk", offsets, t2)
    h = np.einsum("nki,ni->nk", offsets, normals)
    design = np.stack([u * u, u * v, v * v, u, v], axis=-1)  # (N, k, 5)
    # Normal equations per point; a tiny ridge keeps degenerate (collinear) neighbourhoods solvable.
    gram = np.einsum("nki,nkj->nij", design, design)
    scale = np.einsum("nii->n", gram)[:, None, None] * 1e-12 + 1e-300
    coefficients = np.linalg.solve(gram + scale * np.eye(5), np.einsum("nki,nk->ni", design, h)[..., None])
    return -(coefficients[:, 0, 0] + coefficients[:, 2, 0])
