"""A body in the forms users bring: remeshed, decimated, sampled as a point cloud (clean or noisy), scanned
from one side. Every vertex or point of a form carries the ground truth of the body it was made from.

Forms (:data:`FORMS`; one pure function each, from ``(vertices, faces, labels, rng)`` to a :class:`BodyForm`):

``remeshed``     :func:`remeshed_form`: the surface remeshed isotropically by MeshLab (``pymeshlab``), with its
                 own triangulation and vertex count (a per-body random target, 0.55-1.0 times the body's
                 vertex count before the remesher's own rounding), vertices reprojected on the surface and
                 shuffled.
``decimated``    :func:`decimated_form`: quadric decimation to half the faces (``fast_simplification``), left
                 exactly as the simplifier returns it: its non-manifold edges and near-duplicate elements are
                 the point (robustness), so nothing is cleaned.
``cloud``        :func:`cloud_form`: as many points as the body has vertices, uniform on the surface
                 (area-weighted), no faces.
``cloud-noisy``  :func:`noisy_cloud_form`: half as many points, with a density varying smoothly over the
                 surface (a factor 3 between the sparsest and the densest place) and Gaussian noise (default
                 standard deviation 0.002 per coordinate: 2 mm for bodies in metres).
``partial``      :func:`partial_form`: the faces seen from one camera direction (front-facing and not
                 occluded, by an orthographic ray cast from each face's centroid), vertices renumbered.

Ground truth: each vertex or point of a form is a position on the original surface, in barycentric
coordinates of one of its triangles: the point a sample was drawn at (clouds; the noise-free position for
the noisy cloud), the original vertex itself (partial), or the closest point of the original surface
(remeshed, decimated: :func:`closest_points`, exact). The corner with the largest barycentric weight gives
both the template vertex (the original body's vertex index, which is the template's, as every body shares
one topology) and the part label (that vertex's label): :func:`ground_truth`.

The functions work on any triangle mesh (the tests use small procedural ones) and are deterministic for a
given generator state. :func:`make_forms` draws an independent stream for each form from one generator, so
a form does not change with the other forms asked for.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from zernet.data.dataset import DatasetError

__all__ = [
    "FORMS",
    "BodyForm",
    "resolve_forms",
    "check_form_dependencies",
    "make_forms",
    "remeshed_form",
    "decimated_form",
    "cloud_form",
    "noisy_cloud_form",
    "partial_form",
    "closest_points",
    "ground_truth",
    "nonmanifold_edge_count",
    "duplicate_face_count",
]

#: The form names, in the order :func:`make_forms` draws their random streams.
FORMS = ("remeshed", "decimated", "cloud", "cloud-noisy", "partial")

_REMESH_EXTRA_MESSAGE = (
    "the 'remeshed' body form needs pymeshlab: pip install 'zernet[bodies]' (or pip install pymeshlab)"
)
_DECIMATE_EXTRA_MESSAGE = (
    "the 'decimated' body form needs fast-simplification: pip install 'zernet[bodies]' "
    "(or pip install fast-simplification)"
)


@dataclass(frozen=True)
class BodyForm:
    """One form of a body, with ground truth for every vertex or point.

    Attributes:
        name: the form's name (one of :data:`FORMS`).
        vertices: (N, 3) float64 vertex or point positions, in the body's units.
        faces: (F, 3) int64 triangles, or None for a point cloud.
        labels: (N,) int64 part label of each vertex or point (the original body's labels).
        template_vertex: (N,) int64 the original body's (= template's) vertex each one corresponds to.
        details: what was drawn or measured (target counts, camera direction, non-manifold edges, ...).
    """

    name: str
    vertices: np.ndarray
    faces: np.ndarray | None
    labels: np.ndarray
    template_vertex: np.ndarray
    details: dict = field(default_factory=dict)

    @property
    def is_cloud(self) -> bool:
        return self.faces is None


def resolve_forms(forms: str | Sequence[str] | None) -> tuple[str, ...]:
    """Form names from ``None`` / ``""`` (none), ``"all"``, a comma-separated string or a sequence, in
    :data:`FORMS` order without repeats; DatasetError naming an unknown form."""
    if forms is None:
        return ()
    names = [part.strip() for part in forms.split(",")] if isinstance(forms, str) else [str(f) for f in forms]
    names = [name for name in names if name]
    if "all" in names:
        return FORMS
    unknown = sorted(set(names) - set(FORMS))
    if unknown:
        raise DatasetError(f"unknown body form(s) {', '.join(unknown)}; choose from {', '.join(FORMS)} or 'all'")
    return tuple(name for name in FORMS if name in names)


def check_form_dependencies(forms: str | Sequence[str] | None) -> None:
    """DatasetError naming the extra when a form of ``forms`` needs a package that is not installed."""
    import importlib.util

    names = resolve_forms(forms)
    if "remeshed" in names and importlib.util.find_spec("pymeshlab") is None:
        raise DatasetError(_REMESH_EXTRA_MESSAGE)
    if "decimated" in names and importlib.util.find_spec("fast_simplification") is None:
        raise DatasetError(_DECIMATE_EXTRA_MESSAGE)


def make_forms(body, forms: str | Sequence[str] | None, rng: np.random.Generator) -> dict[str, BodyForm]:
    """The forms ``forms`` (see :func:`resolve_forms`) of ``body`` (anything with ``vertices`` (N, 3),
    ``faces`` (F, 3) and ``parts`` (N,)): {name: :class:`BodyForm`}, in :data:`FORMS` order.

    One seed per name of :data:`FORMS` is drawn from ``rng`` first, always all of them, so each form depends
    on ``rng``'s state and its own name only, not on which other forms are made."""
    names = resolve_forms(forms)
    seeds = rng.integers(0, 2**63 - 1, size=len(FORMS))
    makers = {
        "remeshed": remeshed_form,
        "decimated": decimated_form,
        "cloud": cloud_form,
        "cloud-noisy": noisy_cloud_form,
        "partial": partial_form,
    }
    vertices = np.asarray(body.vertices, dtype=np.float64)
    faces = np.asarray(body.faces, dtype=np.int64)
    labels = np.asarray(body.parts, dtype=np.int64)
    return {
        name: makers[name](vertices, faces, labels, np.random.default_rng(seeds[FORMS.index(name)])) for name in names
    }


# ------------------------------------------------------------------------------------------------------
# The forms
# ------------------------------------------------------------------------------------------------------


def remeshed_form(
    vertices: np.ndarray,
    faces: np.ndarray,
    labels: np.ndarray,
    rng: np.random.Generator,
    vertex_ratio: tuple[float, float] = (0.55, 1.0),
    iterations: int = 10,
) -> BodyForm:
    """The surface remeshed isotropically (MeshLab's ``meshing_isotropic_explicit_remeshing``).

    The target edge length is that of an equilateral mesh of the same area with ``r * N`` vertices, ``r``
    drawn uniformly in ``vertex_ratio`` (the remesher then lands some 10-20 % above the target): each body
    gets its own triangulation, not aligned with another body's. Vertices are reprojected on the surface by
    the remesher; their order is shuffled.

    Args:
        vertices: (N, 3) the original body's vertices; faces: (F, 3) its triangles; labels: (N,) its parts.
        rng: draws the target and the order.
        vertex_ratio: range of the target vertex count, as a fraction of N.
        iterations: remeshing iterations (MeshLab's default 10).

    Returns:
        a :class:`BodyForm` with its own (M, 3) vertices and (G, 3) faces; details: ``target_vertices``,
        ``target_edge_length``, ``max_distance`` (largest vertex distance to the original surface).
    """
    try:
        import pymeshlab
    except ImportError as error:
        raise DatasetError(_REMESH_EXTRA_MESSAGE) from error
    vertices, faces = np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64)
    target = int(round(rng.uniform(*vertex_ratio) * len(vertices)))
    area = _face_areas(vertices, faces).sum()
    # Equilateral triangles of side L, F ~ 2V: area = 2V * sqrt(3)/4 * L^2.
    edge_length = float(np.sqrt(2.0 * area / (np.sqrt(3.0) * target)))
    meshes = pymeshlab.MeshSet()
    meshes.add_mesh(pymeshlab.Mesh(vertices, faces))
    # PureValue (absolute length) in pymeshlab >= 2023.12; AbsoluteValue before.
    absolute = getattr(pymeshlab, "PureValue", None) or pymeshlab.AbsoluteValue
    meshes.meshing_isotropic_explicit_remeshing(iterations=int(iterations), targetlen=absolute(edge_length))
    result = meshes.current_mesh()
    new_vertices = np.asarray(result.vertex_matrix(), dtype=np.float64)
    new_faces = np.asarray(result.face_matrix(), dtype=np.int64)
    new_vertices, new_faces = _shuffle_vertices(new_vertices, new_faces, rng)
    face_index, barycentric, _, distance = closest_points(vertices, faces, new_vertices)
    part, template = ground_truth(faces, labels, face_index, barycentric)
    return BodyForm(
        "remeshed",
        new_vertices,
        new_faces,
        part,
        template,
        {
            "target_vertices": target,
            "target_edge_length": edge_length,
            "max_distance": float(distance.max(initial=0.0)),
        },
    )


def decimated_form(
    vertices: np.ndarray, faces: np.ndarray, labels: np.ndarray, rng: np.random.Generator, reduction: float = 0.5
) -> BodyForm:
    """Quadric decimation (``fast_simplification.simplify``) to ``1 - reduction`` of the faces, as returned:
    non-manifold edges, duplicate or degenerate faces and unused vertices the simplifier leaves are kept on
    purpose (a robustness test). Vertex positions are the simplifier's (off the surface by up to a fraction
    of an edge); the order is shuffled by ``rng`` (faces follow).

    Returns:
        a :class:`BodyForm` with (M, 3) vertices and (G, 3) faces; details: ``nonmanifold_edges`` (edges of
        more than 2 faces), ``duplicate_faces``, ``degenerate_faces`` (a repeated corner),
        ``unused_vertices``, ``max_distance`` (largest vertex distance to the original surface).
    """
    try:
        import fast_simplification
    except ImportError as error:
        raise DatasetError(_DECIMATE_EXTRA_MESSAGE) from error
    vertices, faces = np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64)
    new_vertices, new_faces = fast_simplification.simplify(vertices, faces, target_reduction=float(reduction))
    new_vertices = np.asarray(new_vertices, dtype=np.float64)
    new_faces = np.asarray(new_faces, dtype=np.int64)
    new_vertices, new_faces = _shuffle_vertices(new_vertices, new_faces, rng)
    face_index, barycentric, _, distance = closest_points(vertices, faces, new_vertices)
    part, template = ground_truth(faces, labels, face_index, barycentric)
    degenerate = (
        (new_faces[:, 0] == new_faces[:, 1])
        | (new_faces[:, 1] == new_faces[:, 2])
        | (new_faces[:, 0] == new_faces[:, 2])
    )
    return BodyForm(
        "decimated",
        new_vertices,
        new_faces,
        part,
        template,
        {
            "nonmanifold_edges": nonmanifold_edge_count(new_faces),
            "duplicate_faces": duplicate_face_count(new_faces),
            "degenerate_faces": int(degenerate.sum()),
            "unused_vertices": int(len(new_vertices) - len(np.unique(new_faces))),
            "max_distance": float(distance.max(initial=0.0)),
        },
    )


def cloud_form(
    vertices: np.ndarray, faces: np.ndarray, labels: np.ndarray, rng: np.random.Generator, n_points: int | None = None
) -> BodyForm:
    """``n_points`` (default: the body's vertex count) points uniform on the surface (area-weighted), no faces.

    Returns:
        a :class:`BodyForm` with (n_points, 3) vertices and faces None; ground truth from the face and
        barycentric coordinates each point was drawn at.
    """
    vertices, faces = np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64)
    n_points = len(vertices) if n_points is None else int(n_points)
    face_index, barycentric = _sample_faces(_face_areas(vertices, faces), n_points, rng)
    points = np.einsum("mc,mcd->md", barycentric, vertices[faces[face_index]])
    part, template = ground_truth(faces, labels, face_index, barycentric)
    return BodyForm("cloud", points, None, part, template)


def noisy_cloud_form(
    vertices: np.ndarray,
    faces: np.ndarray,
    labels: np.ndarray,
    rng: np.random.Generator,
    fraction: float = 0.5,
    contrast: float = 3.0,
    noise: float = 0.002,
) -> BodyForm:
    """``fraction`` of the body's vertex count as points, with a smoothly varying density, plus noise.

    The density per unit area is ``contrast ** s(x)``, ``s`` a random smooth field scaled to [0, 1] over the
    face centroids: the sum of three plane waves with random directions, phases and wavelengths of 0.5-1
    times the bounding-box diagonal (so the densest place has ``contrast`` times the points per area of the
    sparsest, changing over a body's length, not from face to face). Each point then moves by a Gaussian of
    standard deviation ``noise`` per coordinate (in the mesh's units: 0.002 is 2 mm for bodies in metres).

    Returns:
        a :class:`BodyForm` with (round(fraction * N), 3) noisy points and faces None; ground truth from the
        noise-free position; details: ``noise``, ``contrast``, ``field_directions`` (3, 3),
        ``field_wavelengths`` (3,), ``field_phases`` (3,).
    """
    vertices, faces = np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64)
    n_points = max(1, int(round(fraction * len(vertices))))
    diagonal = float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))
    directions = _unit_vectors(rng, 3)
    wavelengths = diagonal * rng.uniform(0.5, 1.0, size=3)
    phases = rng.uniform(0.0, 2.0 * np.pi, size=3)
    centroids = vertices[faces].mean(axis=1)
    field_value = np.cos(2.0 * np.pi * (centroids @ directions.T) / wavelengths + phases).sum(axis=1)
    span = field_value.max() - field_value.min()
    scaled = (field_value - field_value.min()) / span if span > 0 else np.zeros_like(field_value)
    face_index, barycentric = _sample_faces(_face_areas(vertices, faces) * contrast**scaled, n_points, rng)
    clean = np.einsum("mc,mcd->md", barycentric, vertices[faces[face_index]])
    points = clean + rng.normal(0.0, noise, size=clean.shape)
    part, template = ground_truth(faces, labels, face_index, barycentric)
    return BodyForm(
        "cloud-noisy",
        points,
        None,
        part,
        template,
        {
            "noise": float(noise),
            "contrast": float(contrast),
            "field_directions": directions,
            "field_wavelengths": wavelengths,
            "field_phases": phases,
        },
    )


def partial_form(
    vertices: np.ndarray,
    faces: np.ndarray,
    labels: np.ndarray,
    rng: np.random.Generator,
    direction: np.ndarray | None = None,
    up: np.ndarray = (0.0, 1.0, 0.0),
    max_elevation: float = 20.0,
) -> BodyForm:
    """The part of the surface a camera sees from one side: a one-sided scan.

    The camera looks along ``-direction`` (orthographic; ``direction`` points from the body to the camera).
    By default it is drawn around the ``up`` axis (y: the bodies' up) at a uniform azimuth and an elevation
    within ``max_elevation`` degrees. A face is kept when it faces the camera (normal . direction > 0, with
    the normals turned outward for a closed surface) and the ray from its centroid toward the camera meets
    no other triangle (exact, by point-in-triangle tests in the image plane). The kept faces' vertices are
    renumbered in a shuffled order; their ground truth is their own original index.

    Returns:
        a :class:`BodyForm` with the (M, 3) kept vertices and (G, 3) faces; details: ``direction`` (3,),
        ``kept_faces`` (fraction of the faces).
    """
    vertices, faces = np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64)
    if direction is None:
        up_axis = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
        first, second = _plane_basis(up_axis)
        azimuth = rng.uniform(0.0, 2.0 * np.pi)
        elevation = np.radians(rng.uniform(-max_elevation, max_elevation))
        direction = (
            np.cos(elevation) * (np.cos(azimuth) * first + np.sin(azimuth) * second) + np.sin(elevation) * up_axis
        )
    direction = np.asarray(direction, dtype=np.float64) / np.linalg.norm(direction)
    visible = _visible_faces(vertices, faces, direction)
    kept_faces = faces[visible]
    kept_vertices = np.unique(kept_faces)
    order = rng.permutation(len(kept_vertices))
    kept_vertices = kept_vertices[order]
    new_index = np.full(len(vertices), -1, dtype=np.int64)
    new_index[kept_vertices] = np.arange(len(kept_vertices))
    return BodyForm(
        "partial",
        vertices[kept_vertices],
        new_index[kept_faces],
        labels[kept_vertices].copy(),
        kept_vertices.copy(),
        {"direction": direction, "kept_faces": float(visible.mean())},
    )


# ------------------------------------------------------------------------------------------------------
# Ground truth and counts
# ------------------------------------------------------------------------------------------------------


def ground_truth(
    faces: np.ndarray, labels: np.ndarray, face_index: np.ndarray, barycentric: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(labels (M,), template_vertex (M,)) int64 of M positions given as ``barycentric`` (M, 3) coordinates in
    faces ``face_index`` (M,) of the original mesh: the corner with the largest weight (the first on a tie)
    is the template vertex, and its label the label."""
    corner = np.argmax(barycentric, axis=1)
    template = np.asarray(faces, dtype=np.int64)[face_index, corner]
    return np.asarray(labels, dtype=np.int64)[template], template


def closest_points(
    vertices: np.ndarray, faces: np.ndarray, points: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The exact closest point of a triangle mesh to each of M points.

    Candidates come from a k-d tree of anchors (:func:`_anchors`: points of each face, every point of a face
    within ``R`` of one of them): the faces of the nearest few bound the distance ``d``, and the closest face
    then has an anchor within ``d + R``, so every face with an anchor in that ball is tested exactly
    (Ericson's closest point on a triangle).

    Returns:
        face_index (M,) int64, barycentric (M, 3) float64 (non-negative, summing to 1), closest (M, 3)
        float64 points on the mesh, distance (M,) float64.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    triangles = vertices[faces]
    anchors, anchor_face, reach = _anchors(triangles)
    tree = cKDTree(anchors)
    k = min(8, len(anchors))
    _, nearest = tree.query(points, k=k)
    owners = np.repeat(np.arange(len(points)), k)
    _, bound = _best_per_point(points, triangles, owners, anchor_face[np.asarray(nearest).ravel()], len(points))
    # Slack for rounding: a face exactly at the bound must be in the ball.
    owners, candidates = _ball_faces(tree, anchor_face, points, bound + reach + 1e-9 * (1.0 + reach))
    face_index, distance = _best_per_point(points, triangles, owners, candidates, len(points))
    barycentric = _closest_barycentric(points, triangles[face_index])
    closest = np.einsum("mc,mcd->md", barycentric, triangles[face_index])
    return face_index, barycentric, closest, distance


def nonmanifold_edge_count(faces: np.ndarray) -> int:
    """Undirected edges (pairs of distinct vertices) used by more than two face sides."""
    faces = np.asarray(faces, dtype=np.int64)
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    edges = edges[edges[:, 0] != edges[:, 1]]
    if len(edges) == 0:
        return 0
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return int((counts > 2).sum())


def duplicate_face_count(faces: np.ndarray) -> int:
    """Faces whose vertex set repeats an earlier face's (any order or orientation)."""
    faces = np.asarray(faces, dtype=np.int64)
    if len(faces) == 0:
        return 0
    return int(len(faces) - len(np.unique(np.sort(faces, axis=1), axis=0)))


# ------------------------------------------------------------------------------------------------------
# Helpers
# ------------------------------------------------------------------------------------------------------


def _face_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    triangles = vertices[faces]
    return 0.5 * np.linalg.norm(np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]), axis=1)


def _sample_faces(weights: np.ndarray, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(face_index (n,), barycentric (n, 3)): faces drawn with probability proportional to ``weights``,
    points uniform in each (weights 1 - sqrt(r1), sqrt(r1) (1 - r2), sqrt(r1) r2)."""
    weights = np.asarray(weights, dtype=np.float64)
    if not np.isfinite(weights.sum()) or weights.sum() <= 0:
        raise DatasetError("cannot sample a surface of zero area")
    face_index = rng.choice(len(weights), size=int(n), p=weights / weights.sum()).astype(np.int64)
    r1, r2 = rng.random(int(n)), rng.random(int(n))
    root = np.sqrt(r1)
    return face_index, np.stack([1.0 - root, root * (1.0 - r2), root * r2], axis=1)


def _shuffle_vertices(
    vertices: np.ndarray, faces: np.ndarray, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Vertices in a random order (faces renumbered and shuffled too): the order of a form says nothing."""
    order = rng.permutation(len(vertices))
    new_index = np.empty(len(vertices), dtype=np.int64)
    new_index[order] = np.arange(len(vertices))
    return vertices[order], new_index[faces][rng.permutation(len(faces))]


def _unit_vectors(rng: np.random.Generator, n: int) -> np.ndarray:
    vectors = rng.normal(size=(n, 3))
    return vectors / np.linalg.norm(vectors, axis=1, keepdims=True)


def _plane_basis(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors orthogonal to ``normal`` and to each other."""
    helper = np.eye(3)[np.argmin(np.abs(normal))]
    first = np.cross(normal, helper)
    first /= np.linalg.norm(first)
    return first, np.cross(normal, first)


def _visible_faces(vertices: np.ndarray, faces: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """(F,) bool: faces facing ``direction`` whose centroid's ray along ``direction`` hits no other face."""
    triangles = vertices[faces]
    normals = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    # Turn the normals outward on a closed surface (negative signed volume: inward winding).
    if np.einsum("fi,fi->", triangles[:, 0], normals) < 0:
        normals = -normals
    facing = normals @ direction > 0
    first, second = _plane_basis(direction)
    plane = np.stack([triangles @ first, triangles @ second], axis=2)  # (F, 3, 2) image coordinates
    depth = triangles @ direction  # (F, 3) toward the camera
    centre_plane, centre_depth = plane.mean(axis=1), depth.mean(axis=1)
    anchors, anchor_face, reach = _anchors(plane)
    tested = np.flatnonzero(facing)
    # A triangle containing the image point has an anchor within `reach` of it.
    owners, blockers = _ball_faces(cKDTree(anchors), anchor_face, centre_plane[tested], reach * (1.0 + 1e-9))
    owners = tested[owners]
    other = blockers != owners
    owners, blockers = owners[other], blockers[other]
    # Barycentric coordinates of the ray's image point in each candidate's image triangle.
    a, b, c = plane[blockers, 0], plane[blockers, 1], plane[blockers, 2]
    p = centre_plane[owners]
    v0, v1, v2 = b - a, c - a, p - a
    det = v0[:, 0] * v1[:, 1] - v0[:, 1] * v1[:, 0]
    with np.errstate(divide="ignore", invalid="ignore"):  # a triangle seen edge-on (det 0) hides nothing
        s = (v2[:, 0] * v1[:, 1] - v2[:, 1] * v1[:, 0]) / det
        t = (v0[:, 0] * v2[:, 1] - v0[:, 1] * v2[:, 0]) / det
        inside = (det != 0) & (s >= 0) & (t >= 0) & (s + t <= 1)
        weights = np.stack([1.0 - s - t, s, t], axis=1)
    weights[~inside] = 0.0  # no NaN or infinity from edge-on triangles into the sum
    hit_depth = np.einsum("mc,mc->m", weights, depth[blockers])
    # In front by more than rounding: a neighbour sharing the centroid's plane does not hide it.
    tolerance = 1e-9 * (1.0 + np.abs(depth).max(initial=0.0))
    hidden_by = owners[inside & (hit_depth > centre_depth[owners] + tolerance)]
    visible = facing.copy()
    visible[hidden_by] = False
    return visible


def _anchors(triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Points that cover triangles (F, 3, D) closely: (anchors (A, D), anchor_face (A,), reach R).

    Every point of face f lies within R of one of its anchors. A face whose centroid-to-corner distance is at
    most the median's gets its centroid; a larger one is cut into s x s similar sub-triangles (s = that
    distance over the median, rounded up) and gets their centroids, each within 1/s of its size. A few large
    faces then no longer widen every search ball to their size."""
    centroids = triangles.mean(axis=1)
    sizes = np.linalg.norm(triangles - centroids[:, None], axis=2).max(axis=1)
    target = float(np.median(sizes)) if len(sizes) else 0.0
    if target <= 0:
        return centroids, np.arange(len(triangles)), float(sizes.max(initial=0.0))
    levels = np.maximum(1, np.ceil(sizes / target - 1e-9)).astype(np.int64)
    anchors, anchor_face = [centroids[levels == 1]], [np.flatnonzero(levels == 1)]
    for level in np.unique(levels[levels > 1]):
        chosen = np.flatnonzero(levels == level)
        # Centroids of the level x level sub-triangles, as (x, y) along edges ab, ac in units of 1/level:
        # upward triangles (i, j), i + j <= level - 1, and downward ones, i + j <= level - 2.
        i, j = np.meshgrid(np.arange(level), np.arange(level), indexing="ij")
        up = i + j <= level - 1
        down = i + j <= level - 2
        x = np.concatenate([i[up] + 1.0 / 3.0, i[down] + 2.0 / 3.0]) / level
        y = np.concatenate([j[up] + 1.0 / 3.0, j[down] + 2.0 / 3.0]) / level
        weights = np.stack([1.0 - x - y, x, y], axis=1)  # (S, 3)
        points = np.einsum("sc,fcd->fsd", weights, triangles[chosen])  # (F_level, S, D)
        anchors.append(points.reshape(-1, triangles.shape[2]))
        anchor_face.append(np.repeat(chosen, len(weights)))
    reach = float((sizes / levels).max(initial=0.0))
    return np.concatenate(anchors), np.concatenate(anchor_face), reach


def _ball_faces(
    tree: cKDTree, anchor_face: np.ndarray, points: np.ndarray, radius: np.ndarray | float
) -> tuple[np.ndarray, np.ndarray]:
    """(owner (P,), face (P,)): each point's faces with an anchor within ``radius`` (a face may repeat)."""
    balls = tree.query_ball_point(points, r=radius)
    counts = np.fromiter((len(ball) for ball in balls), dtype=np.int64, count=len(points))
    found = np.fromiter((anchor for ball in balls for anchor in ball), dtype=np.int64, count=int(counts.sum()))
    return np.repeat(np.arange(len(points)), counts), anchor_face[found]


def _best_per_point(
    points: np.ndarray, triangles: np.ndarray, owners: np.ndarray, candidates: np.ndarray, n_points: int
) -> tuple[np.ndarray, np.ndarray]:
    """(face (n_points,), distance (n_points,)): the nearest of each point's candidate faces."""
    face_index = np.zeros(n_points, dtype=np.int64)
    distance = np.full(n_points, np.inf)
    step = 200_000  # pairs per batch: bounded memory on dense balls
    for start in range(0, len(owners), step):
        owner, candidate = owners[start : start + step], candidates[start : start + step]
        barycentric = _closest_barycentric(points[owner], triangles[candidate])
        closest = np.einsum("mc,mcd->md", barycentric, triangles[candidate])
        gap = np.linalg.norm(points[owner] - closest, axis=1)
        # Nearest per owner: sort by (owner, gap), keep the first row of each owner.
        order = np.lexsort((gap, owner))
        first = order[np.r_[True, owner[order][1:] != owner[order][:-1]]]
        better = gap[first] < distance[owner[first]]
        distance[owner[first][better]] = gap[first][better]
        face_index[owner[first][better]] = candidate[first][better]
    return face_index, distance


def _closest_barycentric(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(M, 3) barycentric coordinates of the closest point of each triangle (M, 3, 3) to each point (M, 3)
    (Ericson, Real-Time Collision Detection, 5.1.5: vertex, edge and face regions in that order)."""
    a, b, c = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    ab, ac = b - a, c - a
    ap, bp, cp = points - a, points - b, points - c
    d1, d2 = np.einsum("md,md->m", ab, ap), np.einsum("md,md->m", ac, ap)
    d3, d4 = np.einsum("md,md->m", ab, bp), np.einsum("md,md->m", ac, bp)
    d5, d6 = np.einsum("md,md->m", ab, cp), np.einsum("md,md->m", ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    result = np.zeros((len(points), 3))
    done = np.zeros(len(points), dtype=bool)

    def assign(mask, weights):
        mask = mask & ~done
        result[mask] = weights[mask] if weights.ndim == 2 else weights
        done[mask] = True

    with np.errstate(divide="ignore", invalid="ignore"):
        assign((d1 <= 0) & (d2 <= 0), np.array([1.0, 0.0, 0.0]))
        assign((d3 >= 0) & (d4 <= d3), np.array([0.0, 1.0, 0.0]))
        v = d1 / (d1 - d3)
        assign((vc <= 0) & (d1 >= 0) & (d3 <= 0), np.stack([1.0 - v, v, np.zeros_like(v)], axis=1))
        assign((d6 >= 0) & (d5 <= d6), np.array([0.0, 0.0, 1.0]))
        w = d2 / (d2 - d6)
        assign((vb <= 0) & (d2 >= 0) & (d6 <= 0), np.stack([1.0 - w, np.zeros_like(w), w], axis=1))
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        assign((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), np.stack([np.zeros_like(w), 1.0 - w, w], axis=1))
        total = va + vb + vc
        interior = np.stack([va / total, vb / total, vc / total], axis=1)
    # A degenerate triangle can leave NaN (0/0): fall back to its first corner.
    bad = ~done & ~np.isfinite(interior).all(axis=1)
    interior[bad] = [1.0, 0.0, 0.0]
    assign(np.ones(len(points), dtype=bool), interior)
    result[~np.isfinite(result).all(axis=1)] = [1.0, 0.0, 0.0]
    return result
