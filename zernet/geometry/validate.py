"""Checking a surface and repairing what can be repaired: finite coordinates, index ranges, duplicate
vertices, degenerate faces; reporting non-manifold edges (which every backend accepts).

Public API: :func:`validate_surface`, :func:`repair_surface`, :class:`RepairedSurface`, :func:`check_faces`,
:func:`check_manifold`, :func:`merge_coincident`.
"""

from __future__ import annotations

import logging
import warnings
from dataclasses import dataclass

import numpy as np

from zernet.geometry.surface import Surface, SurfaceError, SurfaceWarning

__all__ = ["validate_surface", "repair_surface", "RepairedSurface", "check_faces", "check_manifold", "merge_coincident"]

logger = logging.getLogger(__name__)

# Coordinates (and extents) must stay within 1/MAX_COORDINATE..MAX_COORDINATE so squared lengths stay finite.
MAX_COORDINATE = 1e150


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
    ================================  ==================================================================

    Non-manifold edges (shared by more than two faces, as simplifiers, scanners and remeshers leave them)
    and vertices that no face uses are kept and reported with a :class:`SurfaceWarning`: the polar
    backends work on them (the front moves over the faces around each vertex, so a third face on an edge
    is one more way forward; an unused vertex gets an empty patch), and vertex indices stay aligned. Repairs are logged at INFO level on the ``zernet.geometry.validate`` logger.

    Args:
        surface: the surface to check.
        repair: apply the repairs above instead of raising for them.

    Returns:
        ``surface`` itself when nothing needed repair, otherwise a repaired copy.
    """
    name = surface.name
    vertices, faces, normals, fields = surface.vertices, surface.faces, surface.normals, dict(surface.fields)
    _check_not_empty(name, vertices, faces)
    _check_coordinates(name, vertices)
    _check_per_vertex_arrays(name, len(vertices), normals, fields)
    if faces is not None:
        _check_face_indices(name, faces, len(vertices))

    repaired = False
    if _report_duplicates(name, vertices, repair):
        vertices, faces, normals, fields = merge_coincident(vertices, faces, normals, fields)
        repaired = True
    if faces is not None:
        faces, dropped = check_faces(name, vertices, faces, repair)
        repaired |= dropped
        check_manifold(name, faces)
        _warn_unused_vertices(name, faces, len(vertices))

    if not repaired:
        return surface
    return Surface(vertices, faces, normals, fields, name)


@dataclass
class RepairedSurface:
    """A repaired surface and where each input vertex went.

    Attributes:
        surface: the repaired surface (duplicates merged, degenerate faces dropped).
        vertex_map: (N_input,) int64 index in ``surface`` of every input vertex (a merged duplicate points
            to the copy that was kept), so ``values[vertex_map]`` gives one value per input vertex.
        merged: number of input vertices merged into another copy.
        dropped_faces: number of degenerate or zero-area faces dropped.
    """

    surface: Surface
    vertex_map: np.ndarray
    merged: int = 0
    dropped_faces: int = 0

    def describe(self) -> str:
        """One line saying what was repaired (empty when nothing was)."""
        parts = []
        if self.merged:
            parts.append(f"merged {self.merged} duplicate vertices")
        if self.dropped_faces:
            parts.append(f"dropped {self.dropped_faces} degenerate faces")
        return ", ".join(parts)


def repair_surface(surface: Surface) -> RepairedSurface:
    """:func:`validate_surface` with ``repair=True``, also returning where each input vertex went.

    What cannot be repaired (empty, NaN, out-of-range faces) raises :class:`SurfaceError` as there. Use it
    to predict on a user's file and hand back one value per *input* vertex: ``values[result.vertex_map]``.
    """
    n_input = surface.n_vertices
    repaired = validate_surface(surface, repair=True)
    if repaired is surface:
        return RepairedSurface(surface, np.arange(n_input, dtype=np.int64))
    _, vertex_map = coincident_numbering(surface.vertices)  # the numbering merge_coincident applied
    dropped = surface.n_faces - repaired.n_faces
    return RepairedSurface(repaired, vertex_map, n_input - repaired.n_vertices, dropped)


def _check_not_empty(name: str, vertices: np.ndarray, faces: np.ndarray | None) -> None:
    if len(vertices) == 0:
        raise SurfaceError(f"{name}: empty surface: 0 vertices")
    if faces is not None and len(faces) == 0:
        raise SurfaceError(f"{name}: empty mesh: 0 faces (for a point cloud, set faces=None)")


def _check_coordinates(name: str, vertices: np.ndarray) -> None:
    """Raise for a non-finite vertex, or coordinates whose squares leave the float64 range."""
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
    if extent > MAX_COORDINATE or 0.0 < span < 1.0 / MAX_COORDINATE:
        raise SurfaceError(
            f"{name}: coordinates reach {extent:.3g} over a span of {span:.3g}; areas (squared lengths) cannot be "
            f"computed in float64 outside 1e-150..1e150: rescale the file"
        )


def _check_per_vertex_arrays(name: str, n: int, normals: np.ndarray | None, fields: dict) -> None:
    """Raise for given normals or fields whose length is not one per vertex, or for unusable normals."""
    if normals is not None:
        if len(normals) != n:
            raise SurfaceError(f"{name}: normals: expected {n} rows (one per vertex), got {len(normals)}")
        length = np.linalg.norm(normals, axis=1)
        bad = np.flatnonzero(~np.isfinite(length) | (length == 0))
        if len(bad):
            raise SurfaceError(
                f"{name}: normal of vertex {bad[0]} is {normals[bad[0]].tolist()} "
                f"({len(bad)} such normals); normals must be finite and non-zero"
            )
    for key, value in fields.items():
        count = value.shape[0] if value.ndim else None
        if count != n:
            raise SurfaceError(
                f"{name}: field {key!r}: expected {n} values (one per vertex), got "
                f"{count if count is not None else 'a scalar'}"
            )


def _check_face_indices(name: str, faces: np.ndarray, n: int) -> None:
    out_of_range = (faces < 0) | (faces >= n)
    if out_of_range.any():
        face, corner = (int(i) for i in np.argwhere(out_of_range)[0])
        raise SurfaceError(
            f"{name}: face {face} = {faces[face].tolist()} refers to vertex {faces[face, corner]}, but "
            f"valid indices are 0..{n - 1} ({int(out_of_range.any(axis=1).sum())} such faces)"
        )


def _report_duplicates(name: str, vertices: np.ndarray, repair: bool) -> bool:
    """Whether some vertices share exactly the same position; raise for them unless repairing."""
    # +0.0 turns -0.0 into 0.0 so that the byte-wise row comparison agrees.
    _, first, inverse, counts = np.unique(
        vertices + 0.0, axis=0, return_index=True, return_inverse=True, return_counts=True
    )
    if not (counts > 1).any():
        return False
    inverse = inverse.reshape(-1)
    duplicate = np.flatnonzero(first[inverse] != np.arange(len(vertices)))
    original = first[inverse[duplicate[0]]]
    if not repair:
        raise SurfaceError(
            f"{name}: vertices {original} and {duplicate[0]} are at the same position "
            f"{vertices[original].tolist()} ({len(duplicate)} duplicate vertices); pass repair=True to "
            "merge them"
        )
    logger.info("%s: merged %d duplicate vertices", name, len(duplicate))
    return True


def _warn_unused_vertices(name: str, faces: np.ndarray, n: int) -> None:
    unused = np.ones(n, dtype=bool)
    unused[faces.ravel()] = False
    if unused.any():
        warnings.warn(
            f"{name}: {int(unused.sum())} vertices are used by no face (first: vertex "
            f"{int(np.flatnonzero(unused)[0])}); kept so that vertex indices and fields stay aligned",
            SurfaceWarning,
            stacklevel=3,  # the caller of validate_surface
        )


def check_faces(name: str, vertices: np.ndarray, faces: np.ndarray, repair: bool) -> tuple[np.ndarray, bool]:
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


def check_manifold(name: str, faces: np.ndarray) -> int:
    """Number of edges shared by more than two faces; a :class:`SurfaceWarning` names the first one.

    Nothing is changed: every polar backend accepts non-manifold edges (see :func:`validate_surface`).
    """
    pairs = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    edges, inverse, counts = np.unique(pairs, axis=0, return_inverse=True, return_counts=True)
    n_bad = int((counts > 2).sum())
    if n_bad:
        worst = int(np.flatnonzero(counts > 2)[0])
        owners = np.flatnonzero(inverse.reshape(-1) == worst) // 3
        warnings.warn(
            f"{name}: {n_bad} non-manifold edges (first: between vertices {edges[worst, 0]} and "
            f"{edges[worst, 1]}, shared by {counts[worst]} faces {owners.tolist()}); kept: patches cross them",
            SurfaceWarning,
            stacklevel=3,
        )
    return n_bad


def merge_coincident(vertices, faces, normals, fields):
    """Merge vertices at exactly the same position into the lowest-numbered copy.

    The kept vertices keep their relative order. For STL, whose vertices are the face corners in order,
    this numbers vertices by first appearance.

    Returns (vertices, faces, normals, fields) remapped; normals and fields take the kept copy's rows.
    """
    kept, new_index = coincident_numbering(vertices)
    merged_faces = None if faces is None else new_index[faces]
    merged_normals = None if normals is None else normals[kept]
    merged_fields = {key: value[kept] for key, value in fields.items()}
    return vertices[kept], merged_faces, merged_normals, merged_fields


def coincident_numbering(vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """How :func:`merge_coincident` numbers vertices: ``(kept, new_index)``, the (K,) lowest-numbered copy of
    each distinct position in increasing order and the (N,) int64 new index of every vertex."""
    # +0.0 turns -0.0 into 0.0 so that the byte-wise row comparison of np.unique agrees with ==.
    _, first, inverse = np.unique(vertices + 0.0, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)  # groups sorted by their lowest vertex index
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return first[order], rank[inverse.reshape(-1)].astype(np.int64)
