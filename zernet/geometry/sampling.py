"""Area normalisation and area-weighted uniform sampling of surfaces.

Public API: :class:`FixedScale`, :func:`normalize_area`, :class:`SurfaceSamples`, :func:`sample_surface`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import scipy.sparse

from zernet.geometry.surface import Surface, SurfaceError

__all__ = ["FixedScale", "normalize_area", "SurfaceSamples", "sample_surface"]


# ====================================================================== area normalisation
@dataclass(frozen=True)
class FixedScale:
    """One linear factor for every surface instead of an area to reach (``patch.scale``).

    For surfaces in known units whose area says nothing about their size: partial scans (one side of a body
    has half its area) and a mix of whole and partial scans from one scanner. ``normalize_area`` then
    multiplies the positions by ``factor`` (about the area-weighted centroid, as it scales for an area).
    """

    factor: float

    def __post_init__(self) -> None:
        if not (np.isfinite(self.factor) and self.factor > 0):
            raise ValueError(f"a fixed scale must be positive and finite, got {self.factor}")


def normalize_area(
    surface: Surface, target_area: float | FixedScale, field_exponents: Mapping[str, float] | None = None
) -> tuple[Surface, float]:
    """Scale a surface uniformly so that its area becomes ``target_area`` (or by a :class:`FixedScale`).

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
        target_area: the wanted area (> 0), e.g. 15000 for human bodies, 100 for aneurysms; or a
            :class:`FixedScale`, whose factor is applied whatever the surface's area.
        field_exponents: {field name: area exponent e}; ``None`` scales no field.

    Returns:
        (scaled surface, s) where s is the linear scale factor applied to the positions.
    """
    fixed = isinstance(target_area, FixedScale)
    if not fixed:
        target_area = float(target_area)
        if not np.isfinite(target_area) or target_area <= 0:
            raise SurfaceError(f"{surface.name}: target area must be positive and finite, got {target_area}")
    field_exponents = dict(field_exponents or {})
    missing = [key for key in field_exponents if key not in surface.fields]
    if missing:
        raise SurfaceError(
            f"{surface.name}: cannot scale missing field(s) {missing} (the surface has {sorted(surface.fields)})"
        )
    weights = surface.vertex_areas()
    area = float(weights.sum())
    if not np.isfinite(area) or area <= 0:
        raise SurfaceError(f"{surface.name}: cannot normalise a surface of area {area}")
    ratio = target_area.factor**2 if fixed else target_area / area
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
    if surface.is_point_cloud:
        return _cloud_samples(surface)
    n_samples = int(n_samples)
    if n_samples < 1:
        raise SurfaceError(f"{surface.name}: n_samples must be at least 1, got {n_samples}")
    areas = surface.face_areas()
    total = areas.sum()
    if not np.isfinite(total) or total <= 0:
        raise SurfaceError(f"{surface.name}: cannot sample a mesh of total area {total}")

    uniform = np.random.default_rng(seed).random((n_samples, 3))  # columns: face choice, r1, r2
    face_index = _pick_faces(areas, uniform[:, 0])
    root = np.sqrt(uniform[:, 1])
    barycentric = np.stack([1.0 - root, root * (1.0 - uniform[:, 2]), root * uniform[:, 2]], axis=1)
    corners = surface.faces[face_index]  # (M, 3)
    return SurfaceSamples(
        points=np.einsum("mc,mcd->md", barycentric, surface.vertices[corners]),
        normals=surface.face_normals()[face_index],
        face_index=face_index,
        barycentric=barycentric,
        interpolation=_interpolation_matrix(corners, barycentric, surface.n_vertices),
    )


def _cloud_samples(surface: Surface) -> SurfaceSamples:
    """The points of a cloud as its own samples (identity interpolation)."""
    n = surface.n_vertices
    return SurfaceSamples(
        points=surface.vertices.copy(),
        normals=surface.vertex_normals(),
        face_index=None,
        barycentric=np.tile([1.0, 0.0, 0.0], (n, 1)),
        interpolation=scipy.sparse.identity(n, dtype=np.float64, format="csr"),
    )


def _pick_faces(areas: np.ndarray, uniform: np.ndarray) -> np.ndarray:
    """(M,) int64 faces chosen with probability proportional to area by inverse CDF of ``uniform`` in [0, 1)."""
    cumulative = np.cumsum(areas)
    face_index = np.searchsorted(cumulative, uniform * cumulative[-1], side="right")
    # Guard the rounding edge case u * total == cumulative[-1]; step back to the last face with area.
    return np.minimum(face_index, np.flatnonzero(areas > 0)[-1]).astype(np.int64)


def _interpolation_matrix(corners: np.ndarray, barycentric: np.ndarray, n_vertices: int) -> scipy.sparse.csr_matrix:
    """(M, N) CSR matrix with each sample's barycentric weights at its face's three vertices."""
    n_samples = len(corners)
    # Copies: scipy may sort the index arrays in place, which must not permute `barycentric`.
    interpolation = scipy.sparse.csr_matrix(
        (barycentric.ravel().copy(), corners.ravel().copy(), np.arange(0, 3 * n_samples + 1, 3)),
        shape=(n_samples, n_vertices),
    )
    interpolation.sum_duplicates()  # a face with a repeated vertex index would otherwise store it twice
    return interpolation
