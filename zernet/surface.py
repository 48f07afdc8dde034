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
import logging
import os
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.io
import scipy.sparse
import trimesh
from scipy.sparse.csgraph import breadth_first_order, connected_components, minimum_spanning_tree
from scipy.spatial import cKDTree

__all__ = [
    "SurfaceError",
    "SurfaceWarning",
    "Surface",
    "load_surface",
    "validate_surface",
    "normalize_area",
    "SurfaceSamples",
    "sample_surface",
]

logger = logging.getLogger(__name__)

# Coordinates (and extents) must stay within 1/_MAX_COORDINATE.._MAX_COORDINATE so squared lengths stay finite.
_MAX_COORDINATE = 1e150
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
        curvature = self._cached("mean_curvature", self._cloud_mean_curvature if self.is_point_cloud
                                 else self._mesh_mean_curvature)
        if smoothing_steps <= 0:
            return curvature
        n = self.n_vertices
        if self.is_point_cloud:
            _, neighbours = self._cloud_neighbours()
            rows, cols = np.repeat(np.arange(n), neighbours.shape[1]), neighbours.ravel()
        else:
            rows, cols = self.edges().T
        adjacency = scipy.sparse.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n)).tocsr()
        adjacency = (adjacency + adjacency.T + scipy.sparse.identity(n)).sign()
        weighted = adjacency @ scipy.sparse.diags(self.vertex_areas())
        total = weighted @ np.ones(n)
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
        import potpourri3d as pp3d  # imported here: only curvature needs it, and it is slow to import

        laplacian = pp3d.cotan_laplacian(self.vertices, self.faces)
        areas = self.vertex_areas()
        mean_normal = np.asarray(laplacian @ self.vertices) / (2.0 * np.maximum(areas, 1e-300)[:, None])
        return np.einsum("ij,ij->i", mean_normal, self.vertex_normals())

    def _cloud_mean_curvature(self) -> np.ndarray:
        points, normals = self.vertices, self.vertex_normals()
        _, neighbours = self._cloud_neighbours()
        t1, t2 = _tangent_basis(normals)
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
        t1, t2 = _tangent_basis(self.vertex_normals())
        offsets = points[neighbours] - points[:, None, :]  # (N, k, 3)
        q = np.stack([np.einsum("nki,ni->nk", offsets, t1), np.einsum("nki,ni->nk", offsets, t2)], axis=-1)
        # Voronoi cell of the origin among the projected neighbours q_j: {x : x·q_j <= |q_j|²/2}. Along a
        # direction u its radius is min over q_j with u·q_j > 0 of (|q_j|²/2) / (u·q_j); area = ½∮ρ² dφ.
        phi = (np.arange(_VORONOI_DIRECTIONS) + 0.5) * (2 * np.pi / _VORONOI_DIRECTIONS)
        directions = np.stack([np.cos(phi), np.sin(phi)], axis=1)  # (D, 2)
        half_square = 0.5 * np.einsum("nkc,nkc->nk", q, q)  # (N, k)
        cap = 0.5 * distance[:, -1]  # clip where no neighbour bounds the cell (rim of an open cloud)
        areas = np.empty(len(points))
        for start in range(0, len(points), 2048):  # chunks keep the (chunk, D, k) temporaries small
            chunk = slice(start, start + 2048)
            projection = np.einsum("nkc,dc->ndk", q[chunk], directions)  # (n, D, k)
            with np.errstate(divide="ignore", invalid="ignore"):
                bound = np.where(projection > 0, half_square[chunk, None, :] / projection, np.inf)
            radius = np.minimum(bound.min(axis=2), cap[chunk, None])
            areas[chunk] = 0.5 * (radius**2).sum(axis=1) * (2 * np.pi / _VORONOI_DIRECTIONS)
        return areas


def _tangent_basis(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """An orthonormal tangent basis (t1, t2) per unit normal, each (N, 3), with (t1, t2, n) right-handed."""
    helper = np.where(np.abs(normals[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = _unit_rows(np.cross(normals, helper))
    return t1, np.cross(normals, t1)


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


# ====================================================================== reading
_MESH_EXTENSIONS = (".ply", ".obj", ".off", ".stl")
_CLOUD_EXTENSIONS = (".npy", ".xyz", ".txt")
# PLY vertex properties that are geometry or colour, not per-vertex fields.
_PLY_NON_FIELDS = {"x", "y", "z", "nx", "ny", "nz", "red", "green", "blue", "alpha"}


def load_surface(path: str | os.PathLike, repair: bool = False, fields: Sequence[str] | None = None) -> Surface:
    """Read a mesh or a point cloud and validate it (see :func:`validate_surface`).

    Formats (by extension, case-insensitive):

    - ``.ply .obj .off .stl`` — read with trimesh, ``process=False`` (and ``maintain_order=True`` for OBJ),
      so vertices keep their order in the file: for correspondence the vertex index is the label. A PLY
      without faces is a point cloud, with its ``nx ny nz`` normals if present. Extra PLY vertex
      properties (other than position, normal and colour) become fields. STL stores every triangle with
      its own three corners, so its vertices are merged by exact position, numbered in order of first
      appearance (the original numbering of an STL file's source cannot be recovered).
    - ``.mat`` — the layout of the ZerNet authors' release (MATLAB v5, via scipy.io.loadmat): ``X`` (V, 3)
      positions, ``F`` (T, 3) **1-based** triangle indices (any integer type, e.g. uint16; without ``F``
      the file is a point cloud), and every other array with V rows, e.g. ``J2m`` (V, 1), becomes a field
      (a (V, 1) column becomes shape (V,)).
    - ``.npy`` (numpy array) and ``.xyz`` / ``.txt`` (whitespace-separated text, ``#`` comments) — point
      clouds of shape (N, 3), or (N, 6) with normals in the last three columns.

    Args:
        path: the file.
        repair: passed to :func:`validate_surface` (merge duplicate vertices, drop degenerate faces).
        fields: names of per-vertex fields to keep (for .mat and PLY); ``None`` keeps all. A requested
            name the file does not have is an error.

    Returns:
        the validated :class:`Surface`, ``name`` set to the path.

    Raises:
        SurfaceError: missing file, unknown extension, unreadable file, or any validation error; the
            message names the file.
    """
    name = os.fspath(path)
    if not os.path.isfile(name):
        raise SurfaceError(f"{name}: no such file")
    extension = os.path.splitext(name)[1].lower()
    if extension in _MESH_EXTENSIONS:
        surface = _load_trimesh(name, extension)
    elif extension == ".mat":
        surface = _load_mat(name)
    elif extension in _CLOUD_EXTENSIONS:
        surface = _load_cloud_array(name, extension)
    else:
        known = ", ".join(_MESH_EXTENSIONS + (".mat",) + _CLOUD_EXTENSIONS)
        raise SurfaceError(f"{name}: unknown surface file extension {extension!r} (known: {known})")

    if fields is not None:
        wanted = [str(key) for key in fields]
        missing = [key for key in wanted if key not in surface.fields]
        if missing:
            raise SurfaceError(
                f"{name}: requested field(s) {missing} not in the file (it has {sorted(surface.fields)})"
            )
        surface = Surface(surface.vertices, surface.faces, surface.normals,
                          {key: surface.fields[key] for key in wanted}, name)
    return validate_surface(surface, repair=repair)


def _load_trimesh(name: str, extension: str) -> Surface:
    """Read PLY/OBJ/OFF/STL with trimesh, keeping the file's vertex order."""
    options = {"maintain_order": True} if extension == ".obj" else {}
    try:
        loaded = trimesh.load(name, process=False, **options)
        if isinstance(loaded, trimesh.Scene) and not any(
            isinstance(geometry, trimesh.PointCloud) for geometry in loaded.geometry.values()
        ):
            # Several meshes in one file: trimesh's own concatenation (applies the scene transforms).
            loaded = trimesh.load(name, process=False, force="mesh", **options)
    except Exception as error:  # trimesh raises many types for a malformed file
        raise SurfaceError(f"{name}: cannot read the file: {type(error).__name__}: {error}") from error

    if extension == ".ply":
        _check_ply_counts(name, loaded)
    raw = loaded.metadata.get("_ply_raw", {}).get("vertex", {}).get("data", {}) if extension == ".ply" else {}
    raw = raw if isinstance(raw, Mapping) else {}
    if isinstance(loaded, trimesh.PointCloud):
        vertices = np.asarray(loaded.vertices, dtype=np.float64)
        normals = None
        if all(key in raw for key in ("nx", "ny", "nz")):
            normals = np.concatenate([np.asarray(raw[key], dtype=np.float64).reshape(-1, 1)
                                      for key in ("nx", "ny", "nz")], axis=1)
        return Surface(vertices, None, normals, _ply_fields(raw, len(vertices)), name)
    if not isinstance(loaded, trimesh.Trimesh):
        raise SurfaceError(f"{name}: the file holds a {type(loaded).__name__}, not a mesh or a point cloud")

    vertices = np.asarray(loaded.vertices, dtype=np.float64)
    faces = np.asarray(loaded.faces, dtype=np.int64)
    if extension == ".stl":
        vertices, faces, _, _ = _merge_coincident(vertices, faces, None, {})
    # File normals of a mesh are not kept: the face orientation defines the normals (vertex_normals()).
    return Surface(vertices, faces, None, _ply_fields(raw, len(vertices)), name)


def _check_ply_counts(name: str, loaded) -> None:
    """Compare what trimesh read with the element counts the PLY header declares.

    trimesh silently returns a point cloud (faces dropped) or fewer elements for a truncated PLY; a file
    that is shorter than its header says is an error, never a partial mesh.
    """
    with open(name, "rb") as handle:
        head = handle.read(65536)
    end = head.find(b"end_header")
    if end < 0:
        return  # trimesh read it without a header in the first 64 KiB: nothing to compare against
    declared = {}
    for line in head[:end].decode("ascii", errors="replace").splitlines():
        parts = line.split()
        if len(parts) == 3 and parts[0] == "element" and parts[2].isdigit():
            declared[parts[1]] = int(parts[2])
    n_vertices = len(getattr(loaded, "vertices", ()))
    faces = getattr(loaded, "faces", None)
    n_faces = 0 if faces is None else len(faces)
    want_vertices, want_faces = declared.get("vertex"), declared.get("face", 0)
    # Polygons are split into triangles, so a mesh may hold more triangles than the header's faces.
    if (want_vertices is not None and n_vertices != want_vertices) or n_faces < want_faces:
        raise SurfaceError(
            f"{name}: the header declares {want_vertices} vertices and {want_faces} faces but only {n_vertices} "
            f"vertices and {n_faces} faces could be read (truncated or corrupt file?)"
        )


def _ply_fields(raw: Mapping, n_vertices: int) -> dict[str, np.ndarray]:
    """Per-vertex PLY properties other than position, normal and colour: (N,) float64 arrays (or (N, C)
    for list properties of fixed length)."""
    fields = {}
    for key, values in raw.items():
        values = np.asarray(values)
        if key in _PLY_NON_FIELDS or values.dtype == object or len(values) != n_vertices:
            continue
        values = values.astype(np.float64).reshape(n_vertices, -1)
        fields[key] = values[:, 0] if values.shape[1] == 1 else values
    return fields


def _load_mat(name: str) -> Surface:
    """Read the authors' MATLAB layout: X (V, 3), F (T, 3) 1-based, per-vertex fields."""
    try:
        content = scipy.io.loadmat(name)
    except NotImplementedError as error:  # MATLAB v7.3 files are HDF5
        raise SurfaceError(
            f"{name}: MATLAB v7.3 (HDF5) files are not supported; save with -v7: {error}"
        ) from error
    except Exception as error:
        raise SurfaceError(f"{name}: cannot read the .mat file: {type(error).__name__}: {error}") from error
    arrays = {key: value for key, value in content.items() if not key.startswith("__")}
    if "X" not in arrays:
        raise SurfaceError(f"{name}: no vertex array 'X' in the .mat file (keys: {sorted(arrays)})")
    vertices = np.asarray(arrays.pop("X"))
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise SurfaceError(f"{name}: 'X' must have shape (V, 3), got {vertices.shape}")
    faces = None
    if "F" in arrays:
        one_based = np.asarray(arrays.pop("F"))
        if one_based.ndim != 2 or one_based.shape[1] != 3:
            raise SurfaceError(f"{name}: 'F' must have shape (T, 3), got {one_based.shape}")
        if one_based.dtype.kind not in "biuf":
            raise SurfaceError(f"{name}: 'F' must hold vertex indices (numbers), got {one_based.dtype}")
        if one_based.dtype.kind == "f":
            # MATLAB stores indices as doubles by default; a NaN or 1.5 must not be truncated to an index.
            whole = np.isfinite(one_based) & (one_based == np.round(one_based)) & (np.abs(one_based) < 2.0**53)
            if not whole.all():
                bad = int(np.argwhere(~whole)[0, 0])
                raise SurfaceError(f"{name}: face {bad} = {one_based[bad].tolist()} in 'F' is not a whole vertex "
                                   "index")
        if one_based.size and one_based.min() < 1:
            bad = int(np.argwhere(one_based < 1)[0, 0])
            raise SurfaceError(
                f"{name}: face {bad} = {one_based[bad].tolist()} has an index below 1, but 'F' holds "
                "1-based (MATLAB) vertex indices"
            )
        # uint16 would wrap around on "- 1" for an index of 0; convert first.
        faces = one_based.astype(np.int64) - 1
    n = vertices.shape[0]
    fields = {}
    for key, value in arrays.items():
        value = np.asarray(value)
        if value.ndim in (1, 2) and value.shape[0] == n and np.issubdtype(value.dtype, np.number):
            fields[key] = value[:, 0] if value.ndim == 2 and value.shape[1] == 1 else value
    return Surface(vertices, faces, None, fields, name)


def _load_cloud_array(name: str, extension: str) -> Surface:
    """Read an (N, 3) or (N, 6) array (positions, then normals) from .npy or text."""
    try:
        if extension == ".npy":
            array = np.load(name, allow_pickle=False)
        else:
            array = np.loadtxt(name, dtype=np.float64, comments="#", ndmin=2)
    except Exception as error:
        raise SurfaceError(f"{name}: cannot read the point cloud: {type(error).__name__}: {error}") from error
    array = np.asarray(array)
    if array.ndim != 2 or array.shape[1] not in (3, 6):
        raise SurfaceError(f"{name}: a point cloud array must have shape (N, 3) or (N, 6), got {array.shape}")
    normals = array[:, 3:6] if array.shape[1] == 6 else None
    return Surface(array[:, :3], None, normals, {}, name)


# ====================================================================== validation
def validate_surface(surface: Surface, repair: bool = False) -> Surface:
    """Check a surface and, if asked, repair what can be repaired.

    Checks, each failing with a :class:`SurfaceError` that names ``surface.name`` and the element:

    ================================  ==================================================================
    problem                           with ``repair=True``
    ================================  ==================================================================
    no vertices; mesh with no faces   error
    NaN or infinite coordinate        error (the position is unknown: nothing to repair with)
    given normals: wrong count,       error
    non-finite or zero
    field with a wrong length         error (names the field, expected N, got M)
    face index out of range           error (a corrupt file; dropping faces would hide it)
    duplicate vertices (exactly       merged into the lowest-numbered copy; later copies are removed,
    the same position)                the remaining vertices keep their relative order, faces, fields
                                      and normals are remapped (fields/normals of the kept copy win).
                                      This renumbers vertices, so correspondence by vertex index changes.
    degenerate faces (a repeated      dropped (after merging, so faces collapsed by the merge go too)
    index) and zero-area faces
    (area <= 1e-12 · bbox diagonal²)
    non-manifold edge (shared by      error even with ``repair=True``: which faces to drop is a
    more than two faces)              modelling decision the user must make
    ================================  ==================================================================

    Vertices that no face uses are kept (so vertex indices and fields stay aligned) and reported with a
    :class:`SurfaceWarning`. Repairs are logged at INFO level on the ``zernet.surface`` logger.

    Args:
        surface: the surface to check.
        repair: apply the repairs above instead of raising for them.

    Returns:
        ``surface`` itself when nothing needed repair, otherwise a repaired copy.
    """
    name = surface.name
    vertices, faces, normals, fields = surface.vertices, surface.faces, surface.normals, dict(surface.fields)
    n = len(vertices)
    if n == 0:
        raise SurfaceError(f"{name}: empty surface: 0 vertices")
    if faces is not None and len(faces) == 0:
        raise SurfaceError(f"{name}: empty mesh: 0 faces (for a point cloud, set faces=None)")

    finite = np.isfinite(vertices).all(axis=1)
    if not finite.all():
        bad = np.flatnonzero(~finite)
        raise SurfaceError(
            f"{name}: vertex {bad[0]} has a non-finite coordinate {vertices[bad[0]].tolist()} "
            f"({len(bad)} such vertices); NaN or infinite positions cannot be repaired"
        )
    # Areas are squared lengths: beyond ~1e154 they overflow float64 to inf, below ~1e-154 they underflow to 0,
    # and every face would then look degenerate. Say what is really wrong instead.
    extent = float(np.abs(vertices).max())
    span = float((vertices.max(axis=0) - vertices.min(axis=0)).max())  # no norm: its squares underflow
    if extent > _MAX_COORDINATE or 0.0 < span < 1.0 / _MAX_COORDINATE:
        raise SurfaceError(
            f"{name}: coordinates reach {extent:.3g} over a span of {span:.3g}; areas (squared lengths) cannot be "
            f"computed in float64 outside 1e-150..1e150: rescale the file"
        )
    if normals is not None:
        if len(normals) != n:
            raise SurfaceError(f"{name}: normals: expected {n} rows (one per vertex), got {len(normals)}")
        length = np.linalg.norm(normals, axis=1)
        bad = np.flatnonzero(~np.isfinite(length) | (length == 0))
        if len(bad):
            raise SurfaceError(f"{name}: normal of vertex {bad[0]} is {normals[bad[0]].tolist()} "
                               f"({len(bad)} such normals); normals must be finite and non-zero")
    for key, value in fields.items():
        count = value.shape[0] if value.ndim else None
        if count != n:
            raise SurfaceError(f"{name}: field {key!r}: expected {n} values (one per vertex), got "
                               f"{count if count is not None else 'a scalar'}")

    if faces is not None:
        out_of_range = (faces < 0) | (faces >= n)
        if out_of_range.any():
            face, corner = (int(i) for i in np.argwhere(out_of_range)[0])
            raise SurfaceError(
                f"{name}: face {face} = {faces[face].tolist()} refers to vertex {faces[face, corner]}, but "
                f"valid indices are 0..{n - 1} ({int(out_of_range.any(axis=1).sum())} such faces)"
            )

    repaired = False
    # Duplicate vertices (exact). +0.0 turns -0.0 into 0.0 so that the byte-wise row comparison agrees.
    _, first, inverse, counts = np.unique(vertices + 0.0, axis=0, return_index=True, return_inverse=True,
                                          return_counts=True)
    if (counts > 1).any():
        inverse = inverse.reshape(-1)
        duplicate = np.flatnonzero(first[inverse] != np.arange(n))
        original = first[inverse[duplicate[0]]]
        if not repair:
            raise SurfaceError(
                f"{name}: vertices {original} and {duplicate[0]} are at the same position "
                f"{vertices[original].tolist()} ({len(duplicate)} duplicate vertices); pass repair=True to "
                "merge them"
            )
        vertices, faces, normals, fields = _merge_coincident(vertices, faces, normals, fields)
        logger.info("%s: merged %d duplicate vertices", name, len(duplicate))
        n = len(vertices)
        repaired = True

    if faces is not None:
        faces, dropped = _check_faces(name, vertices, faces, repair)
        repaired |= dropped
        _check_manifold(name, faces)
        unused = np.ones(n, dtype=bool)
        unused[faces.ravel()] = False
        if unused.any():
            warnings.warn(
                f"{name}: {int(unused.sum())} vertices are used by no face (first: vertex "
                f"{int(np.flatnonzero(unused)[0])}); kept so that vertex indices and fields stay aligned",
                SurfaceWarning,
                stacklevel=2,
            )

    if not repaired:
        return surface
    return Surface(vertices, faces, normals, fields, name)


def _check_faces(name: str, vertices: np.ndarray, faces: np.ndarray, repair: bool) -> tuple[np.ndarray, bool]:
    """Find degenerate (repeated index) and zero-area faces; raise, or drop them when repairing.

    Returns the (possibly reduced) faces and whether any were dropped.
    """
    repeated = (faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 2] == faces[:, 0])
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    diagonal = np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0))
    flat = ~repeated & (area <= 1e-12 * diagonal**2)
    bad = repeated | flat
    if not bad.any():
        return faces, False
    if not repair:
        face = int(np.flatnonzero(bad)[0])
        what = "repeats a vertex index" if repeated[face] else f"has zero area ({area[face]:.3g})"
        raise SurfaceError(
            f"{name}: face {face} = {faces[face].tolist()} {what} ({int(repeated.sum())} degenerate and "
            f"{int(flat.sum())} zero-area faces); pass repair=True to drop them"
        )
    faces = faces[~bad]
    logger.info("%s: dropped %d degenerate and %d zero-area faces", name, int(repeated.sum()), int(flat.sum()))
    if len(faces) == 0:
        raise SurfaceError(f"{name}: empty mesh: every face was degenerate or of zero area")
    return faces, True


def _check_manifold(name: str, faces: np.ndarray) -> None:
    """Raise for an edge shared by more than two faces (no repair: see validate_surface)."""
    pairs = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    edges, inverse, counts = np.unique(pairs, axis=0, return_inverse=True, return_counts=True)
    if (counts > 2).any():
        worst = int(np.flatnonzero(counts > 2)[0])
        owners = np.flatnonzero(inverse.reshape(-1) == worst) // 3
        raise SurfaceError(
            f"{name}: non-manifold edge between vertices {edges[worst, 0]} and {edges[worst, 1]}: shared by "
            f"{counts[worst]} faces {owners.tolist()} ({int((counts > 2).sum())} such edges); this cannot be "
            "repaired automatically (not even with repair=True): remove the extra faces"
        )


def _merge_coincident(vertices, faces, normals, fields):
    """Merge vertices at exactly the same position into the lowest-numbered copy.

    The kept vertices keep their relative order. For STL, whose vertices are the face corners in order,
    this numbers vertices by first appearance.

    Returns (vertices, faces, normals, fields) remapped; normals and fields take the kept copy's rows.
    """
    # +0.0 turns -0.0 into 0.0 so that the byte-wise row comparison of np.unique agrees with ==.
    _, first, inverse = np.unique(vertices + 0.0, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)  # groups sorted by their lowest vertex index
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    kept = first[order]
    new_index = rank[inverse.reshape(-1)]
    merged_faces = None if faces is None else new_index[faces]
    merged_normals = None if normals is None else normals[kept]
    merged_fields = {key: value[kept] for key, value in fields.items()}
    return vertices[kept], merged_faces, merged_normals, merged_fields


# ====================================================================== area normalisation
def normalize_area(
    surface: Surface, target_area: float, field_exponents: Mapping[str, float] | None = None
) -> tuple[Surface, float]:
    """Scale a surface uniformly so that its area becomes ``target_area``.

    The scaling is about the area-weighted centroid c (which therefore stays put), not about the origin:
    ``v' = c + s (v - c)`` with linear factor ``s = sqrt(target_area / area)``. Normals are unchanged.
    A point cloud's area is the estimate of :attr:`Surface.area`, which scales exactly by s², so the
    result's estimated area is ``target_area``.

    Fields named in ``field_exponents = {name: e}`` are multiplied by ``(target_area / area) ** e``
    (= s ** (2e)): a quantity proportional to area^e keeps its relation to the geometry. Wall stress
    scales with the square root of area, so use ``{"J2m": 0.5}``, i.e. J2m is multiplied by s. Other
    fields are copied unchanged. (The aneurysm .mat files are already at area 100, so s = 1 for them.)

    Args:
        surface: mesh or point cloud with positive area.
        target_area: the wanted area (> 0), e.g. 15000 for human bodies, 100 for aneurysms.
        field_exponents: {field name: area exponent e}; ``None`` scales no field.

    Returns:
        (scaled surface, s) where s is the linear scale factor applied to the positions.
    """
    target_area = float(target_area)
    if not np.isfinite(target_area) or target_area <= 0:
        raise SurfaceError(f"{surface.name}: target area must be positive and finite, got {target_area}")
    field_exponents = dict(field_exponents or {})
    missing = [key for key in field_exponents if key not in surface.fields]
    if missing:
        raise SurfaceError(f"{surface.name}: cannot scale missing field(s) {missing} "
                           f"(the surface has {sorted(surface.fields)})")
    weights = surface.vertex_areas()
    area = float(weights.sum())
    if not np.isfinite(area) or area <= 0:
        raise SurfaceError(f"{surface.name}: cannot normalise a surface of area {area}")
    ratio = target_area / area
    scale = float(np.sqrt(ratio))
    centroid = weights @ surface.vertices / area
    vertices = centroid + scale * (surface.vertices - centroid)
    fields = {key: value.copy() for key, value in surface.fields.items()}
    for key, exponent in field_exponents.items():
        fields[key] = np.asarray(fields[key], dtype=np.float64) * ratio ** float(exponent)
    normals = None if surface.normals is None else surface.normals.copy()
    faces = None if surface.faces is None else surface.faces.copy()
    return Surface(vertices, faces, normals, fields, surface.name), scale


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
    # Copies: scipy may sort the index arrays in place, which must not permute `barycentric`.
    interpolation = scipy.sparse.csr_matrix(
        (barycentric.ravel().copy(), corners.ravel().copy(), np.arange(0, 3 * n_samples + 1, 3)),
        shape=(n_samples, n),
    )
    interpolation.sum_duplicates()  # a face with a repeated vertex index would otherwise store it twice
    return SurfaceSamples(
        points=points,
        normals=surface.face_normals()[face_index],
        face_index=face_index,
        barycentric=barycentric,
        interpolation=interpolation,
    )
