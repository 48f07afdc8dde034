"""The ``"accurate"`` polar backend: potpourri3d's vector-heat logarithmic map, one solve per source vertex,
over worker processes (see :mod:`zernet.geometry.polar` for the method).

Public API: :func:`accurate_polar`.
"""

from __future__ import annotations

import multiprocessing
import sys
from concurrent.futures import ProcessPoolExecutor

import numpy as np
import potpourri3d as pp3d

from zernet.geometry.polar.fast import ball_pairs
from zernet.geometry.sampling import SurfaceSamples
from zernet.geometry.surface import Surface
from zernet.threads import available_cores

__all__ = ["accurate_polar"]

# This process's solver and the arrays every chunk reads, set once per worker by _init_log_map_worker.
_WORKER: dict = {}


def accurate_polar(surface: Surface, samples: SurfaceSamples, frames: np.ndarray, r0: float, n_jobs: int | None):
    """potpourri3d log maps, one source vertex per solve, over ``n_jobs`` worker processes.

    Returns:
        (center, sample, radius, angle) of the pairs kept (finite, radius ``<= r0``), grouped by center.
    """
    points = surface.vertices
    n = points.shape[0]
    center, sample, _ = ball_pairs(points, samples.points, r0)
    bounds = np.searchsorted(center, np.arange(n + 1))

    if n_jobs is None:
        n_jobs = available_cores()
    n_jobs = max(1, min(int(n_jobs), n))
    # Several chunks per worker so that a slow chunk does not leave the other workers idle.
    chunks = [c for c in np.array_split(np.arange(n), max(1, 4 * n_jobs)) if len(c)]
    tasks = [(c, center[bounds[c[0]] : bounds[c[-1] + 1]], sample[bounds[c[0]] : bounds[c[-1] + 1]]) for c in chunks]
    context = (points, surface.faces, samples.face_index, samples.barycentric, frames, float(r0))
    if n_jobs == 1:
        _init_log_map_worker(*context)
        results = [_log_map_chunk(task) for task in tasks]
    else:
        with ProcessPoolExecutor(
            max_workers=n_jobs,
            mp_context=_process_context(),
            initializer=_init_log_map_worker,
            initargs=context,
        ) as pool:
            results = list(pool.map(_log_map_chunk, tasks))
    if not results:
        return _no_pairs()
    return tuple(np.concatenate(parts) for parts in zip(*results))


def _no_pairs():
    empty = np.zeros(0)
    return empty.astype(np.int64), empty.astype(np.int64), empty, empty


def _process_context():
    """Worker start method: ``fork`` on Linux, the platform default elsewhere.

    ``fork`` starts instantly and works when the caller runs from stdin or a notebook, where ``spawn``
    cannot re-import ``__main__``. It is safe here because the workers only run numpy and potpourri3d
    (no torch, no OpenMP), so locks held by the parent's thread pools are never taken in the child.
    """
    if sys.platform.startswith("linux"):
        return multiprocessing.get_context("fork")
    return multiprocessing.get_context()


def _init_log_map_worker(points, faces, face_index, barycentric, frames, r0):
    """Build this process's potpourri3d solver once (it is reused for every source vertex)."""
    if faces is None:
        solver = pp3d.PointCloudHeatSolver(points)
    else:
        solver = pp3d.MeshVectorHeatSolver(points, faces)
    basis_x, basis_y, _ = (np.asarray(b, dtype=np.float64) for b in solver.get_tangent_frames())
    longest_edge = None
    if faces is not None:
        corners = points[faces]
        longest_edge = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2).max(axis=1)
    _WORKER.update(
        solver=solver,
        faces=faces,
        face_index=face_index,
        barycentric=barycentric,
        frames=frames,
        basis_x=basis_x,
        basis_y=basis_y,
        longest_edge=longest_edge,
        r0=r0,
    )


def _log_map_chunk(task):
    """Polar coordinates of the candidate samples of a chunk of source vertices.

    Args:
        task: (sources, centers, samples): the chunk's source vertices and its candidate pairs, sorted by
            source.

    Returns:
        (center, sample, radius, angle) arrays of the pairs kept (finite and radius <= r0).
    """
    sources, centers, candidates = task
    w = _WORKER
    out = ([], [], [], [])
    bounds = np.searchsorted(centers, np.concatenate([sources, [sources[-1] + 1]]))
    for index, v in enumerate(sources):
        js = candidates[bounds[index] : bounds[index + 1]]
        if len(js) == 0:
            continue
        if w["faces"] is None:
            log_map = np.asarray(w["solver"].compute_log_map(int(v)), dtype=np.float64)
            vectors = log_map[js]
            radius = np.linalg.norm(vectors, axis=1)
        else:
            vectors, radius = _mesh_sample_log_map(int(v), js)
        tangent = vectors[:, :1] * w["basis_x"][v] + vectors[:, 1:] * w["basis_y"][v]
        angle = np.arctan2(tangent @ w["frames"][v, 1], tangent @ w["frames"][v, 0])
        keep = np.isfinite(radius) & np.isfinite(angle) & (radius <= w["r0"])
        out[0].append(np.full(int(keep.sum()), v, dtype=np.int64))
        out[1].append(js[keep])
        out[2].append(radius[keep])
        out[3].append(angle[keep])
    if not out[0]:
        return _no_pairs()
    return tuple(np.concatenate(parts) for parts in out)


def _mesh_sample_log_map(source: int, js: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Log-map vectors (n, 2) and radii (n,) of mesh samples ``js`` around ``source``: barycentric averages
    of their triangle's corner vectors, with the radius taken from the corner distances where the triangle
    straddles the cut locus."""
    w = _WORKER
    log_map = np.asarray(w["solver"].compute_log_map(source, "AffineLocal"), dtype=np.float64)
    corner_index = w["faces"][w["face_index"][js]]  # (n, 3)
    corners = log_map[corner_index]  # (n, 3, 2)
    weights = w["barycentric"][js]
    vectors = np.einsum("nc,ncd->nd", weights, corners)
    lengths = np.linalg.norm(corners, axis=2)
    radius = np.linalg.norm(vectors, axis=1)
    # Across the cut locus the corner vectors disagree in direction: interpolate the distance.
    unit = corners / np.maximum(lengths, 1e-300)[..., None]
    coherence = np.min([np.einsum("nd,nd->n", unit[:, a], unit[:, b]) for a, b in ((0, 1), (1, 2), (0, 2))], axis=0)
    # Only far from the source (a corner farther than twice the triangle's longest edge) can a
    # triangle straddle the cut; near the source wide corner angles are normal.
    far = lengths.min(axis=1) > 2.0 * w["longest_edge"][w["face_index"][js]]
    straddles = (coherence < 0.0) & far
    radius[straddles] = np.einsum("nc,nc->n", weights, lengths)[straddles]
    return vectors, radius
