"""Geodesic polar coordinates of surface samples around every vertex, tangent frames, transport angles.

For every vertex ``p`` and every sample ``j`` within geodesic distance ``r0`` of ``p`` we need the polar
coordinates ``(r, θ)`` of ``j`` in ``p``'s tangent plane (a discrete logarithmic map): ``r`` is the geodesic
distance and ``θ`` the angle of the initial direction of the geodesic, measured from ``p``'s reference
direction ``e1`` towards ``e2 = n × e1`` (so ``(e1, e2, n)`` is right-handed).

Two backends (measurements in ``../shared/GUIDE.md`` section 4 and ``benchmarks/bench_operator.py``):

``"fast"`` (default)
    One k-d tree ball query of the samples around all vertices, then closed-form corrections, all
    vectorised:

    * radius: the Euclidean chord ``c`` lengthened to the arc of the circle that leaves ``p`` tangent to
      its tangent plane and passes through the sample: with ``sin φ = |d·n_p| / c``, ``r = c φ / sin φ``.
      Exact on planes, spheres and along the principal directions of cylinders (normal sections are
      geodesics there), third-order accurate elsewhere; it also gives the right half-circumference for the
      far side of a tube instead of the diameter.
    * angle: the tangent projection of the chord ``d``, minus its third-order bend
      ``(d·n_p / 3) (n_j − n_p)`` projected to the plane (``n_j`` = smoothly interpolated vertex normals at
      the sample). For a geodesic leaving along ``u`` the projected chord is
      ``s u + (s²/6) κ_n dN(u) + O(s⁴)`` and ``κ_n s² / 2 ≈ d·n_p``, ``s dN(u) ≈ n_j − n_p``; removing the
      term leaves the initial direction to fourth order (exact to 1e-5 rad on a cylinder at r = R/2).
    * sheets: a sample is kept only if it is connected to ``p`` through the surface inside a slightly
      enlarged ball — see :func:`_same_sheet`. This rejects the other side of a thin part, touching
      limbs and other connected components, which a Euclidean ball would wrongly include.

``"accurate"``
    potpourri3d's vector-heat logarithmic map (``MeshVectorHeatSolver.compute_log_map``, strategy
    ``AffineLocal``; ``PointCloudHeatSolver.compute_log_map`` for point clouds), one solve per vertex,
    in parallel worker processes. Mesh samples get the log map by barycentric interpolation of the three
    2D log-map vectors of their triangle. That is exact at and next to the source (the log map is linear
    in a flat one-ring) but wrong in a triangle that straddles the cut locus (its vectors point in nearly
    opposite directions and the average is short): there the radius is interpolated from the vectors'
    lengths instead (distance is continuous across the cut) and only the angle from the vectors.
    Samples on other connected components (potpourri returns NaN there) are dropped.

Both backends consider only samples within Euclidean distance ``r0`` (geodesic distance is never
shorter) and keep those with radius ``<= r0``.
"""

from __future__ import annotations

import multiprocessing
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from zernet.surface import Surface, SurfaceSamples

__all__ = ["PolarCoordinates", "tangent_frames", "compute_polar", "transport_angles", "BACKENDS"]

BACKENDS = ("fast", "accurate")

# A neighbour defines e1 only if its offset is mostly tangential (|tangent part| / |offset| above this).
_FRAME_MIN_TANGENTIAL = 0.5
# Neighbours tried for e1 (nearest first) before falling back to a world axis.
_FRAME_NEIGHBOURS = 8
# Point clouds: k-nearest-neighbour graph used for the sheet test, and the largest allowed |d·n| / |d|
# of a graph edge (an edge that leaves the tangent plane steeply jumps between sheets).
_CLOUD_GRAPH_NEIGHBOURS = 6
_CLOUD_GRAPH_MAX_SLOPE = 0.5


@dataclass
class PolarCoordinates:
    """Geodesic polar coordinates of the samples near each vertex, as flat pair lists.

    Attributes:
        center: (P,) int64 vertex ``p`` of each pair, sorted ascending; within one vertex the pairs are
            sorted by increasing radius (so the first ``n`` pairs of a vertex are its ``n`` nearest samples).
        sample: (P,) int64 sample index ``j``.
        radius: (P,) float64 geodesic distance from ``p`` to ``j`` (absolute units), ``<= r0``.
        angle: (P,) float64 θ in ``[-π, π)``, from ``frames[p, 0]`` towards ``frames[p, 1]``.
        frames: (N, 3, 3) float64 per-vertex orthonormal frame, rows ``(e1, e2, normal)``.
        r0: patch radius used.
        backend: name of the backend that produced them.
        seconds: wall-clock time of the computation (frames included).
    """

    center: np.ndarray
    sample: np.ndarray
    radius: np.ndarray
    angle: np.ndarray
    frames: np.ndarray
    r0: float = 0.0
    backend: str = "fast"
    seconds: float = field(default=0.0, compare=False)

    @property
    def n_pairs(self) -> int:
        """P, the number of (vertex, sample) pairs."""
        return int(self.center.shape[0])

    def counts(self) -> np.ndarray:
        """(N,) int64 number of samples within ``r0`` of each vertex."""
        return np.bincount(self.center, minlength=self.frames.shape[0])


# ====================================================================== frames and transport
def tangent_frames(surface: Surface) -> np.ndarray:
    """Per-vertex orthonormal frames ``(e1, e2, n)``.

    ``n`` is :meth:`Surface.vertex_normals`. ``e1`` is the tangent projection of the direction to the
    nearest other vertex (Euclidean, ties broken by the k-d tree's deterministic order) whose offset is
    mostly tangential; if none of the 8 nearest qualifies (e.g. a lone point), the world axis least
    aligned with ``n``, projected. Because the choice depends only on distances between vertices, the
    frames move with the surface under any rigid motion and are permuted with the vertices when these
    are re-indexed (barring exact distance ties). ``e2 = n × e1``.

    Args:
        surface: mesh or point cloud with N vertices.

    Returns:
        (N, 3, 3) float64, rows ``(e1, e2, n)``.
    """
    points = surface.vertices
    normals = surface.vertex_normals()
    n = points.shape[0]
    e1 = np.zeros((n, 3))
    found = np.zeros(n, dtype=bool)
    k = min(_FRAME_NEIGHBOURS, n - 1)
    if k > 0:
        _, index = cKDTree(points).query(points, k=k + 1)
        index = index[:, 1:]  # column 0 is the point itself (or an exact duplicate)
        offset = points[index] - points[:, None, :]  # (N, k, 3)
        tangential = offset - np.einsum("nki,ni->nk", offset, normals)[..., None] * normals[:, None, :]
        length = np.linalg.norm(offset, axis=2)
        tangential_length = np.linalg.norm(tangential, axis=2)
        usable = tangential_length > _FRAME_MIN_TANGENTIAL * np.maximum(length, 1e-300)
        usable &= length > 0
        first = np.argmax(usable, axis=1)
        found = usable[np.arange(n), first]
        chosen = tangential[np.arange(n), first]
        e1[found] = chosen[found] / tangential_length[np.arange(n), first][found, None]
    if not found.all():
        axes = np.eye(3)[np.argmin(np.abs(normals[~found]), axis=1)]
        projected = axes - np.einsum("ni,ni->n", axes, normals[~found])[:, None] * normals[~found]
        e1[~found] = projected / np.linalg.norm(projected, axis=1, keepdims=True)
    e2 = np.cross(normals, e1)
    return np.stack([e1, e2, normals], axis=1)


def transport_angles(frames: np.ndarray, p, q) -> np.ndarray:
    """Angle ``γ_qp`` of q's reference direction as seen in p's frame, after transport from q to p.

    q's frame is turned by the minimal rotation taking ``n_q`` onto ``n_p`` (the discrete Levi-Civita
    transport along the edge), and ``γ_qp`` is the angle of the turned ``e1_q`` in p's ``(e1, e2)`` basis.
    A tangent direction at angle ψ in q's frame therefore has angle ``ψ + γ_qp`` in p's frame, and a
    directional channel ``h_q(ψ)`` reads ``h_q(ψ_p − γ_qp)`` at p. Sign: turning q's frame by ``+δ``
    (``e1_q → cos δ e1_q + sin δ e2_q``) increases ``γ_qp`` by ``δ``; turning p's frame by ``+δ`` decreases
    it by ``δ``. When the normals are exactly opposite the minimal rotation is not unique; the rotation by
    π about ``e1_q`` is used (``e1_q`` is kept).

    Args:
        frames: (N, 3, 3) rows ``(e1, e2, n)``.
        p: (E,) int indices of the receiving vertices.
        q: (E,) int indices of the sending vertices.

    Returns:
        (E,) float64 angles in ``[-π, π)``.
    """
    p = np.asarray(p, dtype=np.int64)
    q = np.asarray(q, dtype=np.int64)
    e1_q, n_q = frames[q, 0], frames[q, 2]
    e1_p, e2_p, n_p = frames[p, 0], frames[p, 1], frames[p, 2]
    axis = np.cross(n_q, n_p)  # sin(angle) * unit axis
    cosine = np.einsum("ei,ei->e", n_q, n_p)
    # Rodrigues' formula for the rotation taking n_q to n_p: R x = c x + a × x + a (a·x) / (1 + c).
    denominator = 1.0 + cosine
    safe = denominator > 1e-12
    scale = np.divide(1.0, denominator, out=np.zeros_like(denominator), where=safe)
    turned = (
        cosine[:, None] * e1_q
        + np.cross(axis, e1_q)
        + axis * (np.einsum("ei,ei->e", axis, e1_q) * scale)[:, None]
    )
    turned[~safe] = e1_q[~safe]  # antipodal normals: rotation by π about e1_q keeps e1_q
    gamma = np.arctan2(np.einsum("ei,ei->e", turned, e2_p), np.einsum("ei,ei->e", turned, e1_p))
    return _wrap_angle(gamma)


# ====================================================================== entry point
def compute_polar(
    surface: Surface,
    samples: SurfaceSamples,
    r0: float,
    backend: str = "fast",
    n_jobs: int | None = None,
) -> PolarCoordinates:
    """Geodesic polar coordinates of the samples within ``r0`` of every vertex.

    Args:
        surface: mesh or point cloud, N vertices.
        samples: M samples on it (:func:`zernet.surface.sample_surface`).
        r0: patch radius (absolute units), > 0.
        backend: ``"fast"`` or ``"accurate"`` (see the module docstring).
        n_jobs: worker processes for ``"accurate"`` (``None``: all available cores; ``1``: in this
            process). Ignored by ``"fast"``.

    Returns:
        :class:`PolarCoordinates` with pairs sorted by (vertex, radius).
    """
    if not r0 > 0:
        raise ValueError(f"r0 must be positive, got {r0}")
    if backend not in BACKENDS:
        raise ValueError(f"unknown polar backend {backend!r}; choose one of {BACKENDS}")
    if surface.is_point_cloud and samples.n_samples != surface.n_vertices:
        raise ValueError(
            f"{surface.name}: point-cloud samples must be the points themselves "
            f"({samples.n_samples} samples for {surface.n_vertices} points)"
        )
    start = time.perf_counter()
    frames = tangent_frames(surface)
    if backend == "fast":
        center, sample, radius, angle = _fast_polar(surface, samples, frames, r0)
    else:
        center, sample, radius, angle = _accurate_polar(surface, samples, frames, r0, n_jobs)
    # Sort by (vertex, radius): one float key (radius < 2 r0, so the vertex term dominates).
    order = np.argsort(center * (2.0 * r0) + np.minimum(radius, 1.999 * r0), kind="stable")
    return PolarCoordinates(
        center=center[order].astype(np.int64),
        sample=sample[order].astype(np.int64),
        radius=radius[order],
        angle=_wrap_angle(angle[order]),
        frames=frames,
        r0=float(r0),
        backend=backend,
        seconds=time.perf_counter() - start,
    )


# ====================================================================== fast backend
def _fast_polar(surface, samples, frames, r0):
    """Ball query + chord-to-arc radius + bend-corrected tangent angle + same-sheet test."""
    points = surface.vertices
    pairs = cKDTree(points).sparse_distance_matrix(cKDTree(samples.points), r0, output_type="ndarray")
    center = pairs["i"].astype(np.int64)
    sample = pairs["j"].astype(np.int64)
    chord_length = pairs["v"]
    # sparse_distance_matrix drops zero distances (a sample exactly on a vertex): add those back.
    zero_center, zero_sample = _exact_coincidences(points, samples.points)
    center = np.concatenate([center, zero_center])
    sample = np.concatenate([sample, zero_sample])
    chord_length = np.concatenate([chord_length, np.zeros(len(zero_center))])

    order = np.argsort(center, kind="stable")
    center, sample, chord_length = center[order], sample[order], chord_length[order]
    keep = _same_sheet(surface, samples, center, sample, r0)
    center, sample, chord_length = center[keep], sample[keep], chord_length[keep]

    normal = frames[center, 2]
    chord = samples.points[sample] - points[center]
    height = np.einsum("pi,pi->p", chord, normal)  # signed offset along p's normal

    # Radius: arc of the circle tangent to p's plane through the sample (see module docstring).
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


def _surface_graph(surface: Surface) -> tuple[np.ndarray, np.ndarray]:
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


def _same_sheet(surface, samples, center, sample, r0) -> np.ndarray:
    """Mask of (vertex p, sample j) pairs where j is reachable from p through the surface near p.

    For every vertex p, take the vertices within ``r0 + h`` of p (``h`` = longest graph edge) and the graph
    edges between them; j is kept if the graph node it belongs to (the first vertex of its triangle, or
    the point itself in a cloud) lies in the same connected piece of that restricted graph as p. A
    geodesic of length ``<= r0`` stays within Euclidean ``r0`` of p, and every triangle it crosses has all
    its vertices within ``r0 + h``, so no true neighbour is lost; pieces that only come close in space (the
    far wall of a thin part, a touching limb, another component) are separated.

    All vertices are done at once: one graph whose nodes are the (p, v) pairs, whose edges are the mesh
    edges copied into every ball that contains both ends, and one call to ``connected_components``.
    Node look-ups go through a dense (vertex block × N) table, filled one block of vertices at a time.

    Args:
        center, sample: (P,) the candidate pairs, sorted by ``center``.

    Returns:
        (P,) bool.
    """
    points = surface.vertices
    n = points.shape[0]
    edges, longest = _surface_graph(surface)
    # Nodes: (p, v) with |x_v - x_p| <= r0 + h, including (p, p), grouped by p.
    near = cKDTree(points).query_pairs(r0 + longest, output_type="ndarray")
    node_p = np.concatenate([near[:, 0], near[:, 1], np.arange(n)])
    node_v = np.concatenate([near[:, 1], near[:, 0], np.arange(n)])
    order = np.argsort(node_p, kind="stable")
    node_p, node_v = node_p[order], node_v[order]
    node_start = np.searchsorted(node_p, np.arange(n + 1))
    pair_start = np.searchsorted(center, np.arange(n + 1))
    # Each undirected edge once (u < w): the undirected component search does not need both directions.
    upper = scipy.sparse.csr_matrix(
        (np.ones(len(edges), dtype=np.int8), (edges.min(axis=1), edges.max(axis=1))), shape=(n, n)
    )
    upper.sum_duplicates()
    sample_node = sample if samples.face_index is None else surface.faces[samples.face_index[sample], 0]

    block = max(1, min(n, 2**23 // max(n, 1)))  # table of at most 8 M int64 entries (64 MB)
    table = np.full((block, n), -1, dtype=np.int64)
    sources, targets = [], []
    sample_slot = np.empty(len(center), dtype=np.int64)
    own = np.empty(n, dtype=np.int64)
    for first in range(0, n, block):
        last = min(n, first + block)
        a, b = node_start[first], node_start[last]
        ids = np.arange(a, b)
        table[node_p[a:b] - first, node_v[a:b]] = ids
        # Edges (p, u) - (p, w) for every graph edge u -> w whose both ends are in p's ball.
        u = node_v[a:b]
        degree = np.diff(upper.indptr)[u]
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
    source = np.concatenate(sources)
    indptr = np.concatenate([[0], np.cumsum(np.bincount(source, minlength=len(node_p)))])
    graph = scipy.sparse.csr_matrix(
        (np.ones(len(source), dtype=np.int8), np.concatenate(targets), indptr), shape=(len(node_p),) * 2
    )
    _, label = connected_components(graph, directed=False)
    reached = sample_slot >= 0
    reached[reached] = label[sample_slot[reached]] == label[own[center[reached]]]
    return reached


# ====================================================================== accurate backend
def _accurate_polar(surface, samples, frames, r0, n_jobs):
    """potpourri3d log maps, one source vertex per solve, over worker processes."""
    points = surface.vertices
    n = points.shape[0]
    pairs = cKDTree(points).sparse_distance_matrix(cKDTree(samples.points), r0, output_type="ndarray")
    zero_center, zero_sample = _exact_coincidences(points, samples.points)
    center = np.concatenate([pairs["i"].astype(np.int64), zero_center])
    sample = np.concatenate([pairs["j"].astype(np.int64), zero_sample])
    order = np.argsort(center, kind="stable")
    center, sample = center[order], sample[order]
    bounds = np.searchsorted(center, np.arange(n + 1))

    if n_jobs is None:
        n_jobs = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    n_jobs = max(1, min(int(n_jobs), n))
    # Several chunks per worker so that a slow chunk does not leave the other workers idle.
    chunks = [c for c in np.array_split(np.arange(n), max(1, 4 * n_jobs)) if len(c)]
    tasks = [(c, center[bounds[c[0]] : bounds[c[-1] + 1]], sample[bounds[c[0]] : bounds[c[-1] + 1]]) for c in chunks]
    context = (
        points,
        surface.faces,
        samples.face_index,
        samples.barycentric,
        frames,
        float(r0),
    )
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
        empty = np.zeros(0)
        return empty.astype(np.int64), empty.astype(np.int64), empty, empty
    return tuple(np.concatenate(parts) for parts in zip(*results))


_WORKER: dict = {}


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
    import potpourri3d as pp

    if faces is None:
        solver = pp.PointCloudHeatSolver(points)
    else:
        solver = pp.MeshVectorHeatSolver(points, faces)
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
            log_map = np.asarray(w["solver"].compute_log_map(int(v), "AffineLocal"), dtype=np.float64)
            corner_index = w["faces"][w["face_index"][js]]  # (n, 3)
            corners = log_map[corner_index]  # (n, 3, 2)
            weights = w["barycentric"][js]
            vectors = np.einsum("nc,ncd->nd", weights, corners)
            lengths = np.linalg.norm(corners, axis=2)
            radius = np.linalg.norm(vectors, axis=1)
            # Across the cut locus the corner vectors disagree in direction: interpolate the distance.
            unit = corners / np.maximum(lengths, 1e-300)[..., None]
            coherence = np.min(
                [np.einsum("nd,nd->n", unit[:, a], unit[:, b]) for a, b in ((0, 1), (1, 2), (0, 2))], axis=0
            )
            # Only far from the source (a corner farther than twice the triangle's longest edge) can a
            # triangle straddle the cut; near the source wide corner angles are normal.
            far = lengths.min(axis=1) > 2.0 * w["longest_edge"][w["face_index"][js]]
            straddles = (coherence < 0.0) & far
            radius[straddles] = np.einsum("nc,nc->n", weights, lengths)[straddles]
        tangent = vectors[:, :1] * w["basis_x"][v] + vectors[:, 1:] * w["basis_y"][v]
        angle = np.arctan2(tangent @ w["frames"][v, 1], tangent @ w["frames"][v, 0])
        keep = np.isfinite(radius) & np.isfinite(angle) & (radius <= w["r0"])
        out[0].append(np.full(int(keep.sum()), v, dtype=np.int64))
        out[1].append(js[keep])
        out[2].append(radius[keep])
        out[3].append(angle[keep])
    if not out[0]:
        empty = np.zeros(0)
        return empty.astype(np.int64), empty.astype(np.int64), empty, empty
    return tuple(np.concatenate(parts) for parts in out)


def _wrap_angle(angle: np.ndarray) -> np.ndarray:
    """Angles mapped to ``[-π, π)``."""
    return np.mod(np.asarray(angle) + np.pi, 2 * np.pi) - np.pi
