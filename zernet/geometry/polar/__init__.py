"""Geodesic polar coordinates of surface samples around every vertex, tangent frames, transport angles.

For every vertex ``p`` and every sample ``j`` within geodesic distance ``r0`` of ``p`` we need the polar
coordinates ``(r, θ)`` of ``j`` in ``p``'s tangent plane (a discrete logarithmic map): ``r`` is the geodesic
distance and ``θ`` the angle of the initial direction of the geodesic, measured from ``p``'s reference
direction ``e1`` towards ``e2 = n × e1`` (so ``(e1, e2, n)`` is right-handed).

Three backends (their speed and accuracy against exact geodesics are measured by
``benchmarks/speed/bench_geodesics.py`` and ``benchmarks/speed/bench_operator.py``). The default (``backend=None``,
:func:`resolve_backend`) is ``"front"``; a point cloud gets it through a triangulation of its own points
(:mod:`zernet.geometry.cloud_mesh`), built before the polar coordinates by the operator builder.

``"fast"`` (:mod:`zernet.geometry.polar.fast`)
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
      enlarged ball — see :func:`zernet.geometry.polar.fast.same_sheet`. This rejects the other side of a
      thin part, touching limbs and other connected components, which a Euclidean ball would wrongly include.

``"accurate"`` (:mod:`zernet.geometry.polar.accurate`)
    potpourri3d's vector-heat logarithmic map (``MeshVectorHeatSolver.compute_log_map``, strategy
    ``AffineLocal``; ``PointCloudHeatSolver.compute_log_map`` for point clouds), one solve per vertex,
    in parallel worker processes. Mesh samples get the log map by barycentric interpolation of the three
    2D log-map vectors of their triangle. That is exact at and next to the source (the log map is linear
    in a flat one-ring) but wrong in a triangle that straddles the cut locus (its vectors point in nearly
    opposite directions and the average is short): there the radius is interpolated from the vectors'
    lengths instead (distance is continuous across the cut) and only the angle from the vectors.
    Samples on other connected components (potpourri returns NaN there) are dropped.

``"front"`` (the default, :mod:`zernet.geometry.polar.front`)
    Local front propagation from every vertex over the triangles, bounded by ``r0`` (the geodesic polar
    coordinates update of Melvær and Reimers 2012), compiled with numba: distances are surface distances,
    so the far side of a fold (between fingers, across an armpit or the crotch) is never reached through
    the air, and a thin tube is measured the shorter way round. The angle is carried along the front as
    an intrinsic fan angle (:mod:`zernet.geometry.polar.fans`) and mapped back to the tangent plane.

All backends consider only samples within Euclidean distance ``r0`` (geodesic distance is never
shorter) and keep those with radius ``<= r0``.

Public API: :data:`BACKENDS`, :class:`PolarCoordinates`, :func:`tangent_frames`, :func:`transport_angles`,
:func:`compute_polar`, :func:`wrap_angle`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from zernet.geometry.polar.accurate import accurate_polar
from zernet.geometry.polar.fast import fast_polar
from zernet.geometry.polar.front import front_polar
from zernet.geometry.sampling import SurfaceSamples
from zernet.geometry.surface import Surface

__all__ = [
    "PolarCoordinates",
    "tangent_frames",
    "compute_polar",
    "transport_angles",
    "wrap_angle",
    "BACKENDS",
    "BACKEND_VERSIONS",
    "resolve_backend",
]

BACKENDS = ("fast", "accurate", "front")
#: Bumped when a backend's output changes, so cached operators built from the old output are rebuilt.
BACKEND_VERSIONS = {"fast": 1, "accurate": 1, "front": 2}

# A neighbour defines e1 only if its offset is mostly tangential (|tangent part| / |offset| above this).
_FRAME_MIN_TANGENTIAL = 0.5
# Neighbours tried for e1 (nearest first) before falling back to a world axis.
_FRAME_NEIGHBOURS = 8


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
    turned = cosine[:, None] * e1_q + np.cross(axis, e1_q) + axis * (np.einsum("ei,ei->e", axis, e1_q) * scale)[:, None]
    turned[~safe] = e1_q[~safe]  # antipodal normals: rotation by π about e1_q keeps e1_q
    gamma = np.arctan2(np.einsum("ei,ei->e", turned, e2_p), np.einsum("ei,ei->e", turned, e1_p))
    return wrap_angle(gamma)


def wrap_angle(angle: np.ndarray) -> np.ndarray:
    """Angles mapped to ``[-π, π)``."""
    return np.mod(np.asarray(angle) + np.pi, 2 * np.pi) - np.pi


# ====================================================================== entry point
def resolve_backend(surface: Surface, backend: str | None) -> str:
    """The backend used on ``surface``: ``backend``, or for ``None`` ``"front"`` (surface distances).

    :func:`compute_polar` itself runs the front on meshes only; :func:`zernet.operators.build_patch_operator`
    and the data pipeline first triangulate a point cloud through its own points
    (:func:`zernet.geometry.cloud_mesh.mesh_from_cloud`), so the front serves clouds as well."""
    return "front" if backend is None else backend


def compute_polar(
    surface: Surface,
    samples: SurfaceSamples,
    r0: float,
    backend: str | None = None,
    n_jobs: int | None = None,
) -> PolarCoordinates:
    """Geodesic polar coordinates of the samples within ``r0`` of every vertex.

    Args:
        surface: mesh or point cloud, N vertices.
        samples: M samples on it (:func:`zernet.geometry.sample_surface`).
        r0: patch radius (absolute units), > 0.
        backend: ``"fast"``, ``"accurate"``, ``"front"`` (see the module docstring; the front needs a mesh:
            triangulate a cloud first with :func:`zernet.geometry.cloud_mesh.mesh_from_cloud`) or ``None``
            (:func:`resolve_backend`: front).
        n_jobs: worker processes for ``"accurate"`` (``None``: all available cores; ``1``: in this
            process). Ignored by ``"fast"``.

    Returns:
        :class:`PolarCoordinates` with pairs sorted by (vertex, radius).
    """
    if not r0 > 0:
        raise ValueError(f"r0 must be positive, got {r0}")
    backend = resolve_backend(surface, backend)
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
        center, sample, radius, angle = fast_polar(surface, samples, frames, r0)
    elif backend == "front":
        center, sample, radius, angle = front_polar(surface, samples, frames, r0)
    else:
        center, sample, radius, angle = accurate_polar(surface, samples, frames, r0, n_jobs)
    # Sort by (vertex, radius): one float key (radius < 2 r0, so the vertex term dominates). The front
    # backend's pairs come sorted already: checking is cheaper than a stable sort of them.
    key = center * (2.0 * r0) + np.minimum(radius, 1.999 * r0)
    if not np.all(key[1:] >= key[:-1]):
        order = np.argsort(key, kind="stable")
        center, sample, radius, angle = center[order], sample[order], radius[order], angle[order]
    return PolarCoordinates(
        center=center.astype(np.int64, copy=False),
        sample=sample.astype(np.int64, copy=False),
        radius=radius,
        angle=wrap_angle(angle),
        frames=frames,
        r0=float(r0),
        backend=backend,
        seconds=time.perf_counter() - start,
    )
