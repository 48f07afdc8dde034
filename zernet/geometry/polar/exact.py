"""Exact polyhedral geodesic polar coordinates of surface samples: the reference the fast backends are
measured against.

The samples (:func:`zernet.geometry.sample_surface`) are inserted into the mesh as vertices
(:func:`refine_with_samples`): every face that holds samples is split by a Delaunay triangulation of its
corners and samples, laid out isometrically in the plane of the face, so the surface and its area are
unchanged and the distance to a sample is a vertex-to-vertex distance. The distances come from the exact
algorithm of Mitchell, Mount and Papadimitriou (MMP) as implemented by Kirsanov's ``geodesic`` library,
through the ``pygeodesic`` package (an optional test and benchmark dependency, imported lazily by
:class:`ExactGeodesics`). The angle of a sample is the direction of the first segment of its exact
geodesic path, projected into the centre's tangent frame.

MMP costs one wavefront propagation per source (plus one per path traced), so the reference is meant for
a subset of centre vertices, a few hundred on a body-sized mesh.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import Delaunay, cKDTree

from zernet.geometry.sampling import SurfaceSamples
from zernet.geometry.surface import Surface, SurfaceError

__all__ = ["refine_with_samples", "ExactGeodesics"]


def refine_with_samples(surface: Surface, samples: SurfaceSamples) -> tuple[np.ndarray, np.ndarray]:
    """The mesh with every sample inserted as a vertex, same surface and area.

    Vertex ``i < N`` of the result is the surface's vertex ``i``; vertex ``N + j`` is sample ``j``. A face
    holding samples is replaced by the Delaunay triangulation of its three corners and its samples in an
    isometric planar layout of the face (its hull edges are the face's edges, so neighbouring faces still
    share them); the new triangles keep the face's orientation.

    Args:
        surface: triangle mesh with N vertices.
        samples: M samples on it, each strictly inside its face (as sampled, almost surely).

    Returns:
        ``(vertices, faces)``: (N + M, 3) float64 and (F', 3) int64.

    Raises:
        SurfaceError: for a point cloud, or when a sample coincides with a corner or another sample.
    """
    if surface.is_point_cloud:
        raise SurfaceError(f"{surface.name}: exact geodesics need a triangle mesh, got a point cloud")
    n = surface.n_vertices
    faces = surface.faces
    order = np.argsort(samples.face_index, kind="stable")
    face_of = samples.face_index[order]
    split, first = np.unique(face_of, return_index=True)
    bounds = np.append(first, len(order))
    kept = np.ones(len(faces), dtype=bool)
    kept[split] = False
    new_faces = [faces[kept]]
    for f, a, b in zip(split, bounds[:-1], bounds[1:]):
        members = order[a:b]
        local = np.concatenate([np.eye(3), samples.barycentric[members]])  # barycentric of all points
        ids = np.concatenate([faces[f], n + members])
        if len(members) == 1:  # fan around the single sample
            triangles = np.array([[0, 1, 3], [1, 2, 3], [2, 0, 3]])
        else:
            triangulation = Delaunay(local @ _planar_layout(surface.vertices[faces[f]]))
            if len(triangulation.coplanar):
                raise SurfaceError(f"{surface.name}: face {f} has a sample on a corner or on another sample")
            triangles = _oriented(triangulation.simplices, local)
        new_faces.append(ids[triangles])
    vertices = np.concatenate([surface.vertices, samples.points])
    return vertices, np.concatenate(new_faces).astype(np.int64)


def _planar_layout(corners: np.ndarray) -> np.ndarray:
    """(3, 2) positions of a triangle's corners in the plane, same edge lengths and orientation."""
    u = corners[1] - corners[0]
    v = corners[2] - corners[0]
    length = np.linalg.norm(u)
    x = u / length
    vx = v @ x
    vy = np.linalg.norm(v - vx * x)
    return np.array([[0.0, 0.0], [length, 0.0], [vx, vy]])


def _oriented(triangles: np.ndarray, barycentric: np.ndarray) -> np.ndarray:
    """Triangles flipped where needed to turn like the parent face (positive area in barycentric terms)."""
    a, b, c = (barycentric[triangles[:, i], 1:] for i in range(3))
    signed = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    flipped = triangles.copy()
    flipped[signed < 0] = triangles[signed < 0][:, [0, 2, 1]]
    return flipped


class ExactGeodesics:
    """MMP geodesics from vertices of a surface to its samples (inserted as vertices).

    Args:
        surface: triangle mesh, N vertices.
        samples: M samples on it.
        frames: (N, 3, 3) per-vertex frames ``(e1, e2, n)`` (:func:`zernet.geometry.tangent_frames`); the
            angle of a sample is measured from ``e1`` towards ``e2``.

    Raises:
        ImportError: when ``pygeodesic`` is not installed (``pip install pygeodesic``).
    """

    def __init__(self, surface: Surface, samples: SurfaceSamples, frames: np.ndarray):
        pygeodesic = _pygeodesic()
        self.n_vertices = surface.n_vertices
        self.frames = frames
        self.vertices, self.faces = refine_with_samples(surface, samples)
        self._sample_tree = cKDTree(samples.points)
        self._points = surface.vertices
        self._algorithm = pygeodesic.PyGeodesicAlgorithmExact(self.vertices, self.faces)

    def distances(self, center: int, limit: float) -> tuple[np.ndarray, np.ndarray]:
        """Exact distances from vertex ``center`` to the samples within Euclidean distance ``limit``.

        Returns:
            ``(sample, distance)``: sample ids sorted ascending and their geodesic distances; ``inf`` where
            the geodesic distance exceeds ``limit`` (the propagation stops there) or the sample is on
            another connected component.
        """
        candidates = np.sort(
            np.asarray(self._sample_tree.query_ball_point(self._points[center], limit), dtype=np.int64)
        )
        if len(candidates) == 0:
            return candidates, np.zeros(0)
        distance, _ = self._algorithm.geodesicDistances(
            np.array([center], dtype=np.int32), (self.n_vertices + candidates).astype(np.int32), float(limit)
        )
        distance = np.asarray(distance, dtype=np.float64)
        distance[~(distance <= limit)] = np.inf  # unreached targets come back as a huge sentinel
        return candidates, distance

    def initial_angles(self, center: int, sample: np.ndarray, radius: float) -> np.ndarray:
        """Angles of the first segments of the exact geodesic paths from ``center`` to ``sample`` (whose
        distances are at most ``radius``), in the centre's frame (the segment projected to the tangent plane).

        The library traces a path only after a propagation without a distance bound (over the whole mesh),
        so the paths are traced on the part of the refined mesh that can hold them: the faces with a point
        within Euclidean distance ``radius`` of the centre (a path of length ``<= radius`` never leaves that
        ball), which gives the same exact paths at a small fraction of the cost.
        """
        pygeodesic = _pygeodesic()
        start = self.vertices[center]
        corners = self.vertices[self.faces]  # (F', 3, 3)
        nearest_corner = np.linalg.norm(corners - start, axis=2).min(axis=1)
        longest_edge = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2).max(axis=1)
        local_faces = self.faces[nearest_corner <= radius + longest_edge]
        used, local_faces = np.unique(local_faces, return_inverse=True)
        local_faces = local_faces.reshape(-1, 3)
        algorithm = pygeodesic.PyGeodesicAlgorithmExact(self.vertices[used], local_faces)
        local_id = np.searchsorted(used, np.concatenate([[center], self.n_vertices + np.asarray(sample)]))
        e1, e2, _ = self.frames[center]
        angles = np.full(len(sample), np.nan)
        for index, target in enumerate(local_id[1:]):
            _, path = algorithm.geodesicDistance(int(local_id[0]), int(target))
            # The library traces the path back from the target: its last point is the source.
            steps = path[::-1] - start
            moved = np.flatnonzero(np.linalg.norm(steps, axis=1) > 1e-12)
            if len(moved):
                step = steps[moved[0]]
                angles[index] = np.arctan2(step @ e2, step @ e1)
        return angles

    def polar(self, centers, r0: float, limit: float | None = None):
        """Exact polar coordinates around each of ``centers``.

        Args:
            centers: vertex ids.
            r0: angles are traced for the samples with distance ``<= r0``.
            limit: distances are computed up to this (default ``1.5 r0``); farther samples get ``inf``.

        Returns:
            ``(center, sample, distance, angle)`` flat arrays over every sample within Euclidean distance
            ``limit`` of its centre; ``angle`` is NaN where the distance exceeds ``r0``.
        """
        limit = 1.5 * r0 if limit is None else float(limit)
        out = ([], [], [], [])
        for center in np.asarray(centers, dtype=np.int64):
            sample, distance = self.distances(int(center), limit)
            angle = np.full(len(sample), np.nan)
            inside = distance <= r0
            if inside.any():
                angle[inside] = self.initial_angles(int(center), sample[inside], float(distance[inside].max()))
            for part, values in zip(out, (np.full(len(sample), center), sample, distance, angle)):
                part.append(values)
        return tuple(np.concatenate(part) if part else np.zeros(0) for part in out)


def _pygeodesic():
    """The optional ``pygeodesic.geodesic`` module, with an install hint when it is missing."""
    try:
        import pygeodesic.geodesic as pygeodesic  # optional: only the reference needs it
    except ImportError as error:
        raise ImportError("exact geodesics need the optional package pygeodesic (pip install pygeodesic)") from error
    return pygeodesic
