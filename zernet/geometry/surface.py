"""The :class:`Surface` data class: a triangle mesh or a point cloud with per-vertex fields.

A :class:`Surface` is either a triangle mesh (``faces`` is an ``(F, 3)`` int64 array) or a point cloud
(``faces is None``). Everything downstream (polar coordinates, patch operators, models) accepts both.

Geometry is float64 numpy throughout. Vertex order is never changed unless the user opts into a repair
(:func:`zernet.geometry.validate_surface` with ``repair=True``), because for correspondence tasks the
vertex index *is* the label.

Public API: :class:`SurfaceError` (every problem with a surface; the message names the file and the
element), :class:`SurfaceWarning` (non-fatal findings), :class:`Surface`.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field

import numpy as np
import potpourri3d as pp3d
import scipy.sparse
from scipy.spatial import cKDTree

from zernet.geometry.pointcloud import (
    CLOUD_NEIGHBOURS,
    nearest_neighbours,
    orient_normals,
    pca_normals,
    quadric_mean_curvature,
    unit_rows,
    voronoi_cell_areas,
)

__all__ = ["SurfaceError", "SurfaceWarning", "Surface"]


class SurfaceError(ValueError):
    """A surface that cannot be read or used. The message names the file (or ``"<array>"``) and the element."""


class SurfaceWarning(UserWarning):
    """A finding about a surface that does not stop it from being used (e.g. unreferenced vertices)."""


@dataclass(eq=False)
class Surface:
    """A triangle mesh or a point cloud with optional per-vertex fields.

    Attributes:
        vertices: (N, 3) float64 positions.
        faces: (F, 3) int64 vertex indices of counter-clockwise triangles, or ``None`` for a point cloud.
        normals: (N, 3) float64 unit normals given by the user or the file, or ``None``. When ``None``,
            :meth:`vertex_normals` computes them (area-weighted face normals, or PCA for clouds).
        fields: per-vertex arrays, each (N,) or (N, C), e.g. ``{"J2m": (N,) wall stress}``.
        name: file path or a short name; every error message names it.

    Construction converts the arrays to the documented dtypes and checks their shapes; the full checks
    (NaN, index range, degenerate faces, ...) live in :func:`zernet.geometry.validate_surface`.
    """

    vertices: np.ndarray
    faces: np.ndarray | None = None
    normals: np.ndarray | None = None
    fields: dict[str, np.ndarray] = field(default_factory=dict)
    name: str = "<array>"

    def __post_init__(self) -> None:
        self.name = str(self.name)
        self.vertices = _as_float_array(self.vertices, "vertices", self.name)
        if self.faces is not None:
            self.faces = _as_face_array(self.faces, self.name)
        if self.normals is not None:
            self.normals = _as_float_array(self.normals, "normals", self.name)
        self.fields = {str(key): np.asarray(value) for key, value in dict(self.fields).items()}
        # Derived quantities (normals, vertex areas) cached under the geometry hash, so that mutating the
        # arrays in place simply invalidates them instead of returning stale values.
        self._cache: dict[tuple[str, str], np.ndarray] = {}

    # ------------------------------------------------------------------ basic properties
    @property
    def n_vertices(self) -> int:
        """N, the number of vertices (points)."""
        return int(self.vertices.shape[0])

    @property
    def n_faces(self) -> int:
        """F, the number of triangles (0 for a point cloud)."""
        return 0 if self.faces is None else int(self.faces.shape[0])

    @property
    def is_point_cloud(self) -> bool:
        """True when the surface has no faces."""
        return self.faces is None

    @property
    def area(self) -> float:
        """Surface area.

        Mesh: exact sum of triangle areas. Point cloud: estimated as the sum of :meth:`vertex_areas`, the
        per-point tangent-plane Voronoi cell areas (see there); within a few per cent on evenly or randomly
        sampled smooth surfaces, and exactly proportional to the square of any uniform scaling.
        """
        if self.is_point_cloud:
            return float(self.vertex_areas().sum())
        return float(self.face_areas().sum())

    # ------------------------------------------------------------------ geometry
    def face_areas(self) -> np.ndarray:
        """Triangle areas, shape (F,) float64. Raises :class:`SurfaceError` for a point cloud."""
        self._require_mesh("face_areas")
        return 0.5 * np.linalg.norm(self._face_cross(), axis=1)

    def face_normals(self) -> np.ndarray:
        """Unit triangle normals (right-hand rule over the face's vertex order), shape (F, 3).

        Zero-area faces get a zero vector. Raises :class:`SurfaceError` for a point cloud.
        """
        self._require_mesh("face_normals")
        cross = self._face_cross()
        length = np.linalg.norm(cross, axis=1, keepdims=True)
        return np.divide(cross, length, out=np.zeros_like(cross), where=length > 0)

    def vertex_areas(self) -> np.ndarray:
        """Area attributed to each vertex, shape (N,) float64; sums to :attr:`area`.

        Mesh: one third of the area of every incident triangle (barycentric cells).
        Point cloud: the area of the point's Voronoi cell among its nearest neighbours projected on its
        tangent plane (normal from :meth:`vertex_normals`). In directions without neighbours (the rim of
        an open cloud) the cell is clipped at half the distance to the 16th nearest neighbour.
        """
        if not self.is_point_cloud:
            areas = np.zeros(self.n_vertices)
            np.add.at(areas, self.faces.ravel(), np.repeat(self.face_areas() / 3.0, 3))
            return areas
        return self._cached("cloud_vertex_areas", self._cloud_vertex_areas)

    def vertex_normals(self) -> np.ndarray:
        """Unit normal per vertex, shape (N, 3) float64.

        - If :attr:`normals` was given, those (normalised to unit length).
        - Mesh: area-weighted average of the incident face normals (the unnormalised cross products are
          summed, so larger faces weigh more). A vertex that no face uses takes the normal of the nearest
          vertex that has one.
        - Point cloud: PCA of the 16 nearest points (the direction of least variance), oriented
          consistently by propagating along a minimum spanning tree of the neighbour graph (Hoppe et al.
          1992), starting in each connected part from the point with the largest x, whose normal is
          made to point towards +x — outward for a closed surface.
        """
        if self.normals is not None:
            return unit_rows(self.normals)
        if self.is_point_cloud:
            return self._cached("cloud_normals", self._cloud_normals)
        return self._cached("mesh_normals", self._mesh_normals)

    def mean_curvature(self, smoothing_steps: int = 0) -> np.ndarray:
        """Signed mean curvature per vertex, shape (N,) float64: ``1/R`` on a sphere of radius R with outward
        normals, ``1/(2R)`` on a cylinder, 0 on a plane; negative where the surface bends away from its normal.

        - Mesh: ``H_i = (L x)_i · n_i / (2 A_i)``, L the cotangent Laplacian (positive semi-definite) and A_i
          the vertex area (:meth:`vertex_areas`), n_i from :meth:`vertex_normals`. On a boundary vertex this
          is a one-sided estimate (the surface does not continue past the cut).
        - Point cloud: a quadric ``h = a u² + b uv + c v² + d u + e v`` fitted by least squares to the 16
          nearest neighbours in the tangent frame of :meth:`vertex_normals`; ``H = -(a + c)``.

        ``smoothing_steps`` rounds of averaging each vertex with its neighbours (mesh edges, or the 16
        nearest points), weighted by vertex area, remove the discretisation noise of irregular sampling.
        """
        curvature = self._cached(
            "mean_curvature", self._cloud_mean_curvature if self.is_point_cloud else self._mesh_mean_curvature
        )
        if smoothing_steps <= 0:
            return curvature
        weighted = self._area_weighted_adjacency()
        total = weighted @ np.ones(self.n_vertices)
        for _ in range(smoothing_steps):
            curvature = (weighted @ curvature) / total
        return curvature

    def edges(self) -> np.ndarray:
        """Unique undirected mesh edges as sorted vertex pairs (i < j), shape (E, 2) int64, lexicographic
        order. A point cloud has no edges: shape (0, 2)."""
        if self.is_point_cloud:
            return np.zeros((0, 2), dtype=np.int64)
        return np.unique(self._directed_face_edges_sorted(), axis=0)

    def boundary_vertices(self) -> np.ndarray:
        """Mask of vertices on a boundary edge (an edge used by exactly one face), shape (N,) bool.
        All False for a point cloud."""
        mask = np.zeros(self.n_vertices, dtype=bool)
        if self.is_point_cloud or self.n_faces == 0:
            return mask
        edges, counts = np.unique(self._directed_face_edges_sorted(), axis=0, return_counts=True)
        mask[edges[counts == 1].ravel()] = True
        return mask

    def geometry_hash(self) -> str:
        """sha256 hex digest of the geometry: shapes and little-endian bytes of vertices (float64), faces
        (int64; a marker for point clouds) and the given normals when present (they define the tangent
        planes of a cloud). Stable across runs and platforms; fields and name do not enter it."""
        digest = hashlib.sha256()
        digest.update(b"zernet-surface-v1")
        digest.update(np.asarray(self.vertices.shape, dtype="<i8").tobytes())
        digest.update(np.ascontiguousarray(self.vertices, dtype="<f8").tobytes())
        if self.faces is None:
            digest.update(b"point-cloud")
        else:
            digest.update(np.asarray(self.faces.shape, dtype="<i8").tobytes())
            digest.update(np.ascontiguousarray(self.faces, dtype="<i8").tobytes())
        if self.normals is not None:
            digest.update(b"normals")
            digest.update(np.ascontiguousarray(self.normals, dtype="<f8").tobytes())
        return digest.hexdigest()

    # ------------------------------------------------------------------ copies
    def copy(self) -> Surface:
        """A deep copy (all arrays copied)."""
        return Surface(
            vertices=self.vertices.copy(),
            faces=None if self.faces is None else self.faces.copy(),
            normals=None if self.normals is None else self.normals.copy(),
            fields={key: value.copy() for key, value in self.fields.items()},
            name=self.name,
        )

    def with_fields(self, fields: dict[str, np.ndarray] | None = None, **more: np.ndarray) -> Surface:
        """A new Surface with the same geometry (arrays shared, not copied) and ``fields`` merged over the
        existing ones (a later value replaces an earlier one of the same name)."""
        merged = dict(self.fields)
        merged.update(fields or {})
        merged.update(more)
        return Surface(self.vertices, self.faces, self.normals, merged, self.name)

    def __repr__(self) -> str:
        kind = "point cloud" if self.is_point_cloud else f"mesh, {self.n_faces} faces"
        return f"Surface({self.name!r}, {self.n_vertices} vertices, {kind}, fields={sorted(self.fields)})"

    # ------------------------------------------------------------------ internals
    def _require_mesh(self, what: str) -> None:
        if self.is_point_cloud:
            raise SurfaceError(f"{self.name}: {what} needs a mesh, but this surface is a point cloud")

    def _face_cross(self) -> np.ndarray:
        """(F, 3) cross products (b - a) x (c - a); their length is twice the triangle area."""
        a, b, c = (self.vertices[self.faces[:, i]] for i in range(3))
        return np.cross(b - a, c - a)

    def _directed_face_edges_sorted(self) -> np.ndarray:
        """(3F, 2) the three edges of every face, each as a sorted vertex pair, face-major order."""
        pairs = self.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
        return np.sort(pairs, axis=1)

    def _cached(self, key: str, compute) -> np.ndarray:
        cache_key = (key, self.geometry_hash())
        if cache_key not in self._cache:
            self._cache.clear()  # only ever keep values for the current geometry
            self._cache[cache_key] = compute()
        return self._cache[cache_key].copy()

    def _area_weighted_adjacency(self) -> scipy.sparse.csr_matrix:
        """(N, N) neighbour graph with self-loops (mesh edges, or the 16 nearest points of a cloud), each
        column weighted by its vertex area: one step of area-weighted neighbour averaging."""
        n = self.n_vertices
        if self.is_point_cloud:
            _, neighbours = self._cloud_neighbours()
            rows, cols = np.repeat(np.arange(n), neighbours.shape[1]), neighbours.ravel()
        else:
            rows, cols = self.edges().T
        adjacency = scipy.sparse.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n)).tocsr()
        adjacency = (adjacency + adjacency.T + scipy.sparse.identity(n)).sign()
        return adjacency @ scipy.sparse.diags(self.vertex_areas())

    def _mesh_normals(self) -> np.ndarray:
        normals = np.zeros_like(self.vertices)
        cross = self._face_cross()
        for corner in range(3):
            np.add.at(normals, self.faces[:, corner], cross)
        length = np.linalg.norm(normals, axis=1)
        missing = length == 0
        normals = np.divide(normals, length[:, None], out=np.zeros_like(normals), where=~missing[:, None])
        if missing.any():
            if missing.all():
                raise SurfaceError(f"{self.name}: no face has a non-zero area, so no normal can be computed")
            # Vertices no (non-degenerate) face touches: borrow the nearest real normal.
            have = np.flatnonzero(~missing)
            _, nearest = cKDTree(self.vertices[have]).query(self.vertices[missing])
            normals[missing] = normals[have[nearest]]
        return normals

    def _mesh_mean_curvature(self) -> np.ndarray:
        laplacian = pp3d.cotan_laplacian(self.vertices, self.faces)
        areas = self.vertex_areas()
        mean_normal = np.asarray(laplacian @ self.vertices) / (2.0 * np.maximum(areas, 1e-300)[:, None])
        return np.einsum("ij,ij->i", mean_normal, self.vertex_normals())

    def _cloud_neighbours(self) -> tuple[np.ndarray, np.ndarray]:
        """Distances and indices of the k nearest other points, each (N, k), k = min(16, N - 1)."""
        n = self.n_vertices
        if n < 3:
            raise SurfaceError(f"{self.name}: a point cloud needs at least 3 points, got {n}")
        return nearest_neighbours(self.vertices, min(CLOUD_NEIGHBOURS, n - 1))

    def _cloud_normals(self) -> np.ndarray:
        _, neighbours = self._cloud_neighbours()
        return orient_normals(self.vertices, pca_normals(self.vertices, neighbours), neighbours)

    def _cloud_vertex_areas(self) -> np.ndarray:
        distance, neighbours = self._cloud_neighbours()
        return voronoi_cell_areas(self.vertices, self.vertex_normals(), distance, neighbours)

    def _cloud_mean_curvature(self) -> np.ndarray:
        _, neighbours = self._cloud_neighbours()
        return quadric_mean_curvature(self.vertices, self.vertex_normals(), neighbours)


def _as_float_array(values, what: str, name: str) -> np.ndarray:
    """Convert to a C-contiguous (N, 3) float64 array or raise :class:`SurfaceError`."""
    try:
        array = np.ascontiguousarray(values, dtype=np.float64)
    except (TypeError, ValueError) as error:
        raise SurfaceError(f"{name}: {what} are not numeric: {error}") from error
    if array.ndim != 2 or array.shape[1] != 3:
        raise SurfaceError(f"{name}: {what} must have shape (N, 3), got {array.shape}")
    return array


def _as_face_array(values, name: str) -> np.ndarray:
    """Convert to a C-contiguous (F, 3) int64 array; integral floats are accepted, never truncated."""
    faces = np.asarray(values)
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise SurfaceError(f"{name}: faces must have shape (F, 3), got {faces.shape}")
    if faces.size and not np.issubdtype(faces.dtype, np.integer):
        # Some readers produce integral floats: accept those, but a 2.5 or a NaN is an error.
        if not np.all(np.isfinite(faces)) or np.any(faces != np.round(faces)):
            bad = int(np.argwhere(~np.isfinite(faces) | (faces != np.round(faces)))[0, 0])
            raise SurfaceError(f"{name}: face {bad} has non-integer vertex indices {faces[bad].tolist()}")
    return np.ascontiguousarray(faces, dtype=np.int64)
