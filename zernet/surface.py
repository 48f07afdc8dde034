"""Surfaces: triangle meshes and point clouds, their reading, validation, area normalisation and sampling.

A :class:`Surface` is either a triangle mesh (``faces`` is an ``(F, 3)`` int64 array) or a point cloud
(``faces is None``). Everything downstream (polar coordinates, patch operators, models) accepts both.

Geometry is float64 numpy throughout. Vertex order is never changed unless the user opts into a repair
(:func:`validate_surface` with ``repair=True``), because for correspondence tasks the vertex index *is*
the label.

Public API
----------
- :class:`SurfaceError` — every problem with a surface; the message names the file and the element.
- :class:`SurfaceWarning` — non-fatal findings (e.g. vertices that no face uses).
- :class:`Surface` — the data class.
- :func:`load_surface`, :func:`validate_surface`, :func:`normalize_area`.
- :class:`SurfaceSamples`, :func:`sample_surface` — area-weighted uniform samples with barycentric weights.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse
from scipy.sparse.csgraph import breadth_first_order, connected_components, minimum_spanning_tree
from scipy.spatial import cKDTree

__all__ = [
    "SurfaceError",
    "SurfaceWarning",
    "Surface",
    "SurfaceSamples",
    "sample_surface",
]

# Neighbourhood size for point-cloud normal estimation (PCA) and area estimation.
_CLOUD_NEIGHBOURS = 16
# Number of directions used to integrate the tangent-plane Voronoi cell of a cloud point.
_VORONOI_DIRECTIONS = 128


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
    (NaN, index range, degenerate faces, ...) live in :func:`validate_surface`.
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
            faces = np.asarray(self.faces)
            if faces.ndim != 2 or faces.shape[1] != 3:
                raise SurfaceError(f"{self.name}: faces must have shape (F, 3), got {faces.shape}")
            if faces.size and not np.issubdtype(faces.dtype, np.integer):
                # Accept integral floats (some readers produce them) but never silently truncate.
                if not np.all(np.isfinite(faces)) or np.any(faces != np.round(faces)):
                    bad = int(np.argwhere(~np.isfinite(faces) | (faces != np.round(faces)))[0, 0])
                    raise SurfaceError(
                        f"{self.name}: face {bad} has non-integer vertex indices {faces[bad].tolist()}"
                    )
            self.faces = np.ascontiguousarray(faces, dtype=np.int64)
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
            return _unit_rows(self.normals)
        if self.is_point_cloud:
            return self._cached("cloud_normals", self._cloud_normals)
        return self._cached("mesh_normals", self._mesh_normals)

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

    def _cloud_neighbours(self) -> tuple[np.ndarray, np.ndarray]:
        """Distances and indices of the k nearest other points, each (N, k), k = min(16, N - 1)."""
        n = self.n_vertices
        if n < 3:
            raise SurfaceError(f"{self.name}: a point cloud needs at least 3 points, got {n}")
        k = min(_CLOUD_NEIGHBOURS, n - 1)
        distance, index = cKDTree(self.vertices).query(self.vertices, k=k + 1)
        return distance[:, 1:], index[:, 1:]  # column 0 is the point itself

    def _cloud_normals(self) -> np.ndarray:
        points = self.vertices
        _, neighbours = self._cloud_neighbours()
        # PCA over each point and its neighbours: the eigenvector of the smallest eigenvalue.
        patch = np.concatenate([points[:, None, :], points[neighbours]], axis=1)
        centred = patch - patch.mean(axis=1, keepdims=True)
        covariance = np.einsum("nki,nkj->nij", centred, centred)
        _, vectors = np.linalg.eigh(covariance)
        normals = vectors[:, :, 0]

        # Consistent orientation: flip along a spanning tree that prefers nearly parallel normals.
        n, k = neighbours.shape
        rows = np.repeat(np.arange(n), k)
        cols = neighbours.ravel()
        alignment = np.abs(np.einsum("ij,ij->i", normals[rows], normals[cols]))
        weight = 1.0 - alignment + 1e-9  # strictly positive: csgraph treats 0 as "no edge"
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
        return _unit_rows(normals)

    def _cloud_vertex_areas(self) -> np.ndarray:
        points = self.vertices
        distance, neighbours = self._cloud_neighbours()
        normals = self.vertex_normals()
        # Orthonormal tangent basis (t1, t2) per point.
        helper = np.where(np.abs(normals[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
        t1 = _unit_rows(np.cross(normals, helper))
        t2 = np.cross(normals, t1)
        offsets = points[neighbours] - points[:, None, :]  # (N, k, 3)
        q = np.stack([np.einsum("nki,ni->nk", offsets, t1), np.einsum("nki,ni->nk", offsets, t2)], axis=-1)
        # Voronoi cell of the origin among the projected neighbours q_j: {x : x·q_j <= |q_j|²/2}. Along a
        # direction u its radius is min over q_j with u·q_j > 0 of (|q_j|²/2) / (u·q_j); area = ½∮ρ² dφ.
        phi = (np.arange(_VORONOI_DIRECTIONS) + 0.5) * (2 * np.pi / _VORONOI_DIRECTIONS)
        directions = np.stack([np.cos(phi), np.sin(phi)], axis=1)  # (D, 2)
        half_square = 0.5 * np.einsum("nkc,nkc->nk", q, q)  # (N, k)
        projection = np.einsum("nkc,dc->ndk", q, directions)  # (N, D, k)
        cap = 0.5 * distance[:, -1]  # clip where no neighbour bounds the cell (rim of an open cloud)
        with np.errstate(divide="ignore", invalid="ignore"):
            radius = np.where(projection > 0, half_square[:, None, :] / projection, np.inf).min(axis=2)
        radius = np.minimum(radius, cap[:, None])
        return 0.5 * (radius**2).sum(axis=1) * (2 * np.pi / _VORONOI_DIRECTIONS)


def _as_float_array(values, what: str, name: str) -> np.ndarray:
    """Convert to a C-contiguous (N, 3) float64 array or raise :class:`SurfaceError`."""
    try:
        array = np.ascontiguousarray(values, dtype=np.float64)
    except (TypeError, ValueError) as error:
        raise SurfaceError(f"{name}: {what} are not numeric: {error}") from error
    if array.ndim != 2 or array.shape[1] != 3:
        raise SurfaceError(f"{name}: {what} must have shape (N, 3), got {array.shape}")
    return array


def _unit_rows(vectors: np.ndarray) -> np.ndarray:
    """Rows scaled to unit length; zero rows stay zero."""
    vectors = np.asarray(vectors, dtype=np.float64)
    length = np.linalg.norm(vectors, axis=1, keepdims=True)
    return np.divide(vectors, length, out=np.zeros_like(vectors), where=length > 0)


# ====================================================================== sampling
@dataclass(eq=False)
class SurfaceSamples:
    """Points on a surface and the linear map that carries per-vertex fields to them.

    Attributes:
        points: (M, 3) float64 sample positions.
        normals: (M, 3) float64 unit normals (the face normal for mesh samples, the vertex normal for
            cloud samples).
        face_index: (M,) int64 face each sample lies on, or ``None`` for a point cloud (sample i = vertex i).
        barycentric: (M, 3) float64 weights of the face's three vertices (rows sum to 1); for a point
            cloud every row is (1, 0, 0).
        interpolation: scipy.sparse.csr_matrix (M, N): ``interpolation @ f`` gives the piecewise-linear
            value at the samples of a per-vertex field ``f`` of shape (N,) or (N, C).
    """

    points: np.ndarray
    normals: np.ndarray
    face_index: np.ndarray | None
    barycentric: np.ndarray
    interpolation: scipy.sparse.csr_matrix

    @property
    def n_samples(self) -> int:
        """M, the number of samples."""
        return int(self.points.shape[0])


def sample_surface(surface: Surface, n_samples: int, seed: int = 0) -> SurfaceSamples:
    """Area-weighted uniform samples on a surface, reproducible for a given seed.

    Mesh: each sample picks a face with probability proportional to its area (inverse-CDF on the
    cumulative areas, so zero-area faces are never picked), then a uniform point in the triangle with
    barycentric weights (1 - √r1, √r1 (1 - r2), √r1 r2) for r1, r2 uniform on [0, 1). All randomness comes
    from ``numpy.random.default_rng(seed)`` in a fixed order, so the same surface and seed give
    bit-identical samples.

    Point cloud: the samples are the points themselves (M = N, interpolation = identity) and
    ``n_samples`` is ignored — there is no surface between the points to sample from, and the points
    already carry the field values exactly.

    Args:
        surface: a mesh or a point cloud.
        n_samples: M, number of samples for a mesh (>= 1).
        seed: seed of the random generator.

    Returns:
        :class:`SurfaceSamples` with M samples on an N-vertex surface.
    """
    n = surface.n_vertices
    if surface.is_point_cloud:
        return SurfaceSamples(
            points=surface.vertices.copy(),
            normals=surface.vertex_normals(),
            face_index=None,
            barycentric=np.tile([1.0, 0.0, 0.0], (n, 1)),
            interpolation=scipy.sparse.identity(n, dtype=np.float64, format="csr"),
        )

    n_samples = int(n_samples)
    if n_samples < 1:
        raise SurfaceError(f"{surface.name}: n_samples must be at least 1, got {n_samples}")
    areas = surface.face_areas()
    total = areas.sum()
    if not np.isfinite(total) or total <= 0:
        raise SurfaceError(f"{surface.name}: cannot sample a mesh of total area {total}")

    rng = np.random.default_rng(seed)
    uniform = rng.random((n_samples, 3))  # columns: face choice, r1, r2
    cumulative = np.cumsum(areas)
    face_index = np.searchsorted(cumulative, uniform[:, 0] * cumulative[-1], side="right")
    # Guard the rounding edge case u * total == cumulative[-1]; step back to the last face with area.
    face_index = np.minimum(face_index, np.flatnonzero(areas > 0)[-1]).astype(np.int64)

    root = np.sqrt(uniform[:, 1])
    barycentric = np.stack([1.0 - root, root * (1.0 - uniform[:, 2]), root * uniform[:, 2]], axis=1)
    corners = surface.faces[face_index]  # (M, 3)
    points = np.einsum("mc,mcd->md", barycentric, surface.vertices[corners])
    interpolation = scipy.sparse.csr_matrix(
        (barycentric.ravel(), corners.ravel(), np.arange(0, 3 * n_samples + 1, 3)), shape=(n_samples, n)
    )
    interpolation.sum_duplicates()  # a face with a repeated vertex index would otherwise store it twice
    return SurfaceSamples(
        points=points,
        normals=surface.face_normals()[face_index],
        face_index=face_index,
        barycentric=barycentric,
        interpolation=interpolation,
    )
