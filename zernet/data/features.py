"""Per-vertex model inputs: the input parts a feature kind joins, and how each is computed.

A feature kind joins registered parts with "+" (e.g. ``"xyz+normals"`` or ``"shape+curvature+membrane"``);
:func:`compute_features` puts the parts' channels side by side in that order and :func:`feature_channels`
says how many there are before any surface is loaded. The parts are a registry, :data:`FEATURE_PARTS`:
the built-in ones are registered at the end of this module, and a higher layer adds its own with
:func:`register_input_part` (``template``, which runs a trained model, registers from
:mod:`zernet.matching.template`). A feature kind naming a part not registered yet imports the module that
declares it under the entry-point group :data:`INPUT_PART_ENTRY_POINTS`, so callers need not know who provides it.
"""

from __future__ import annotations

import importlib.metadata
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse
from scipy.spatial import cKDTree

from zernet.data.dataset import DatasetError
from zernet.geometry import Surface, membrane_stress
from zernet.zernike import harmonic_pairs, index_to_nm, orders

__all__ = [
    "InputPart",
    "FEATURE_PARTS",
    "INPUT_PART_ENTRY_POINTS",
    "register_input_part",
    "MEMBRANE_PRESTRESSES",
    "HKS_EIGENPAIRS",
    "HKS_TIMES",
    "BOUNDARY_SATURATION",
    "default_features",
    "feature_parts",
    "feature_channels",
    "feature_slices",
    "needs_patch_operators",
    "shape_descriptors",
    "curvature_descriptors",
    "membrane_descriptors",
    "heat_kernel_descriptors",
    "compute_features",
]


@dataclass(frozen=True)
class InputPart:
    """One input part: its channel count and how it is computed.

    Attributes:
        name: what a feature kind calls it (no "+").
        width: its channels, or a function of the patch scales' Zernike degrees giving them.
        compute: ``compute(surface, operators, cache_dir) -> (N, width)`` array; ``operators`` are the
            surface's patch operators, one per scale (None when the data set builds none).
        reads_operators: the part is computed from the patch operators (then they are always built).
    """

    name: str
    width: int | Callable[[Sequence[int]], int]
    compute: Callable
    reads_operators: bool = False

    def channels(self, degrees: Sequence[int]) -> int:
        return int(self.width(degrees) if callable(self.width) else self.width)


#: The registered input parts by name (:func:`register_input_part`).
FEATURE_PARTS: dict[str, InputPart] = {}

#: Entry-point group of the modules that register input parts from above this layer (zernet's own
#: ``template`` part, ``zernet.matching.template``, is declared in pyproject.toml; other packages may add
#: theirs): a feature kind naming an unregistered part imports the module that provides it, so no caller has
#: to import it first and nothing here imports a higher layer by name.
INPUT_PART_ENTRY_POINTS = "zernet.input_parts"


def register_input_part(
    name: str, width: int | Callable[[Sequence[int]], int], compute: Callable, reads_operators: bool = False
) -> InputPart:
    """Add input part ``name`` (see :class:`InputPart`); registering the same function again (a module
    reloaded) replaces it, another function under a taken name is a ValueError."""
    if not name or "+" in name:
        raise ValueError(f"an input part's name is non-empty and has no '+': {name!r}")
    existing = FEATURE_PARTS.get(name)
    if existing is not None and (existing.compute.__module__, existing.compute.__qualname__) != (
        compute.__module__,
        compute.__qualname__,
    ):
        raise ValueError(f"input part {name!r} is already registered by {existing.compute.__module__}")
    FEATURE_PARTS[name] = InputPart(name, width, compute, reads_operators)
    return FEATURE_PARTS[name]


#: Eigenpairs of the Laplacian behind the "hks" part: its times run from ``4 ln 10 / λ_64`` (a few patch
#: radii on a body) to ``4 ln 10 / λ_1`` (the whole surface).
HKS_EIGENPAIRS = 64
#: Times of the heat kernel signature: the channels of the "hks" part.
HKS_TIMES = 16

#: Pre-tensions of the :func:`~zernet.geometry.membrane.membrane_stress` channels of the "membrane" feature part.
MEMBRANE_PRESTRESSES = (0.01, 0.02, 0.04)

#: Distance to the boundary, in units of r0, beyond which the boundary feature saturates.
BOUNDARY_SATURATION = 3.0


def default_features(surface: Surface) -> np.ndarray:
    """The default model input: vertex positions centred at the area-weighted centroid, (N, 3) float32.

    The centroid is ``Σ_i a_i x_i / Σ_i a_i`` with ``a_i`` the per-vertex areas of
    :meth:`Surface.vertex_areas` (a third of the incident triangle areas; estimated cell areas for point
    clouds), i.e. the centroid of the surface as a thin shell, not of its vertex set: it does not move when
    one region is meshed more densely than another. It is the point about which
    :func:`~zernet.geometry.sampling.normalize_area` scales, so centring does not depend on the normalisation.
    No rotation is removed: the features are as rotation-dependent as the surface's placement.
    """
    weights = surface.vertex_areas()
    centroid = weights @ surface.vertices / weights.sum()
    return (surface.vertices - centroid).astype(np.float32)


def feature_parts(kind: str) -> list[str]:
    """The registered parts of feature kind ``kind`` ("+"-joined), in order, after loading the providers of
    unregistered ones (:data:`INPUT_PART_ENTRY_POINTS`); DatasetError if one is still unknown."""
    parts = str(kind).split("+")
    _load_provided_parts({part for part in parts if part not in FEATURE_PARTS})
    unknown = [part for part in parts if part not in FEATURE_PARTS]
    if unknown or len(set(parts)) != len(parts):
        raise DatasetError(
            f"unknown feature kind {kind!r}: join distinct parts of {sorted(FEATURE_PARTS)} "
            "with '+', e.g. 'xyz+normals' or 'shape+curvature+membrane'"
        )
    return parts


def _load_provided_parts(names: set[str]) -> None:
    """Import the modules that declare (by entry point) the input parts ``names``: importing registers them."""
    if not names:
        return
    for entry in importlib.metadata.entry_points(group=INPUT_PART_ENTRY_POINTS):
        if entry.name in names:
            try:
                entry.load()
            except Exception as error:  # a broken provider is named, not hidden behind "unknown part"
                raise DatasetError(
                    f"input part {entry.name!r}: its provider {entry.value} failed to load: {error}"
                ) from error
            if entry.name not in FEATURE_PARTS:
                raise DatasetError(f"input part {entry.name!r}: {entry.value} loaded but did not register it")


def feature_channels(kind: str, n_max=5) -> int:
    """Number of input channels of feature ``kind``; ``n_max``: the degree of each patch scale (int or list)."""
    degrees = [n_max] if isinstance(n_max, int) else list(n_max)
    return sum(FEATURE_PARTS[part].channels(degrees) for part in feature_parts(kind))


def feature_slices(kind: str, degrees: Sequence[int]) -> dict[str, slice]:
    """The columns of each part of feature ``kind`` (``degrees``: the Zernike degree of each patch scale)."""
    slices, start = {}, 0
    for part in feature_parts(kind):
        width = FEATURE_PARTS[part].channels(list(degrees))
        slices[part] = slice(start, start + width)
        start += width
    return slices


def shape_descriptors(surface: Surface, operator, boundary: bool = True) -> np.ndarray:
    """Rotation-invariant local shape descriptors from a patch operator, (N, P + 1) float32.

    The height of each patch sample above the tangent plane of its centre vertex p,
    ``h = (x - x_p) · n_p``, is fitted with Zernike polynomials by the patch operator itself (the height
    is linear in the vertex positions, so ``A @ X`` projected on ``n_p`` gives its coefficients). Rotating
    p's reference direction turns each pair ``(a_n^m, a_n^-m)`` by ``m φ``, so the ``m = 0`` coefficients
    and the pair norms ``sqrt(a_n^m² + a_n^-m²)`` do not depend on it: P = number of ``(n, |m|)``
    pairs (12 for n_max = 5). ``Z_2^0`` is the mean curvature term, ``|Z_2^±2|`` the anisotropy of the
    curvature, higher orders finer shape. Values are divided by r0 to be scale-free. They are also
    invariant under rigid motions of the surface, unlike xyz.

    With ``boundary`` (default), a last channel is the Euclidean distance from each vertex to the nearest boundary vertex divided by
    r0 and saturated at :data:`BOUNDARY_SATURATION` (closed surfaces: the saturation value everywhere), so
    a model can learn what the truncated patches near a cut boundary look like.
    """
    matrix = operator.matrix
    n, k = surface.n_vertices, operator.k
    normals = surface.vertex_normals()
    positions = surface.vertices
    coeffs = (matrix @ positions).reshape(n, k, 3)
    constant = np.asarray(matrix @ np.ones(n)).reshape(n, k)
    heights = np.einsum("nkc,nc->nk", coeffs, normals) - constant * np.einsum("nc,nc->n", positions, normals)[:, None]
    r0 = float(operator.config.r0)
    m = orders(operator.n_max)
    zero, cos_idx, sin_idx, _ = harmonic_pairs(operator.n_max)
    invariants = [heights[:, j] for j in zero]
    invariants += [np.hypot(heights[:, c], heights[:, s_]) for c, s_ in zip(cos_idx, sin_idx)]
    # Order the columns by (n, |m|) so they read like the basis.
    keys = [index_to_nm(j) for j in zero] + [index_to_nm(c) for c in cos_idx]
    order = sorted(range(len(keys)), key=lambda i: keys[i])
    assert len(order) == int((m >= 0).sum())
    descriptors = np.stack([invariants[i] for i in order], axis=1) / r0
    if not boundary:
        return descriptors.astype(np.float32)

    on_boundary = surface.boundary_vertices()
    if on_boundary.any():
        distance, _ = cKDTree(positions[on_boundary]).query(positions)
        distance = np.minimum(distance / r0, BOUNDARY_SATURATION)
    else:
        distance = np.full(n, BOUNDARY_SATURATION)
    return np.concatenate([descriptors, distance[:, None]], axis=1).astype(np.float32)


def curvature_descriptors(surface: Surface, radii: Sequence[float]) -> np.ndarray:
    """Mean curvature at the vertex and averaged over balls of the given radii, (N, 1 + len(radii)) float32.

    Column 0 is :meth:`Surface.mean_curvature` times ``radii[0]``; column 1 + s is the area-weighted mean
    of it over the vertices within Euclidean distance ``radii[s]``, times ``radii[s]`` (dimensionless: r/R
    on a sphere of radius R). Why: membrane stress follows the curvature of the wall at the scale of the
    sac (Laplace's law, σ ∝ 1/H), which per-vertex estimates are too noisy and patch fits too truncated
    near cuts to give. On the aneurysm leave-one-out these channels took a per-vertex MLP on the ``shape``
    descriptors from 11.1 % to 10.5 % MAPE. Invariant under rigid motions and vertex re-indexing; the sign
    follows the normals' orientation, like the ``m = 0`` height descriptors.
    """
    if not len(radii):
        raise DatasetError("curvature_descriptors needs at least one radius")
    curvature = surface.mean_curvature()
    areas = surface.vertex_areas()
    tree = cKDTree(surface.vertices)
    n = surface.n_vertices
    columns = [curvature * radii[0]]
    for radius in radii:
        # Sparse ball-membership matrix B (N, N), area-weighted: each row averages over one ball.
        pairs = tree.query_pairs(radius, output_type="ndarray")
        rows = np.concatenate([pairs[:, 0], pairs[:, 1], np.arange(n)])
        cols = np.concatenate([pairs[:, 1], pairs[:, 0], np.arange(n)])
        ball = scipy.sparse.csr_matrix((areas[cols], (rows, cols)), shape=(n, n))
        columns.append(radius * (ball @ curvature) / (ball @ np.ones(n)))
    return np.stack(columns, axis=1).astype(np.float32)


def needs_patch_operators(kind: str) -> bool:
    """Whether feature ``kind`` has a part computed from the surface's patch operators."""
    return any(FEATURE_PARTS[part].reads_operators for part in feature_parts(kind))


def compute_features(surface: Surface, kind: str = "xyz", operators=None, cache_dir=None) -> np.ndarray:
    """Model input of feature kind ``kind``, (N, C) float32: its parts side by side.

    The built-in parts:

    - ``"xyz"``: :func:`default_features` (3);
    - ``"normals"``: unit vertex normals (3);
    - ``"ones"``: a constant 1 per vertex (the model then sees geometry only through the patch operators'
      frames and sampling, useful as an ablation);
    - ``"shape"``: :func:`shape_descriptors` at every patch scale, then the boundary distance in units of the
      first scale's r0 (rotation- and translation-invariant);
    - ``"curvature"``: :func:`curvature_descriptors` at the patch scales' radii;
    - ``"membrane"``: log of :func:`~zernet.geometry.membrane.membrane_stress` at each of
      :data:`MEMBRANE_PRESTRESSES` (meshes only; cached in ``cache_dir`` when given);
    - ``"hks"``: :func:`heat_kernel_descriptors` (16; meshes and point clouds; the eigenbasis cached in
      ``cache_dir`` when given).

    Registered by :mod:`zernet.matching`: ``"template"``, human bodies only: where on the template body each
    vertex lies, read by the template model shipped with zernet (3; meshes and point clouds in any pose;
    cached in ``cache_dir`` when given). The same for one place on every person, unlike xyz: a model trained
    on a few people carries to new ones.

    ``operators``: the surface's patch operators, one per scale (needed by "shape" and "curvature").
    """
    columns = []
    for name in feature_parts(kind):
        part = FEATURE_PARTS[name]
        if part.reads_operators and not operators:
            raise DatasetError(f"feature part {name!r} of {kind!r} needs the surface's patch operators")
        columns.append(np.asarray(part.compute(surface, operators, cache_dir), dtype=np.float32))
    return np.concatenate(columns, axis=1)


def membrane_descriptors(surface: Surface, cache_dir=None) -> np.ndarray:
    """log of the membrane stress under unit inner pressure at each :data:`MEMBRANE_PRESTRESSES`, (N, 3).

    Why: for stress targets this solves the wall's equilibrium (see :mod:`zernet.geometry.membrane`) instead of asking
    the network to learn it from a few shapes. The log makes a scaled stress a shifted feature. A point
    cloud has no wall: DatasetError naming the shape.
    """
    if surface.is_point_cloud:
        raise DatasetError(f"{surface.name}: feature part 'membrane' needs a triangle mesh, got a point cloud")
    stresses = np.stack([membrane_stress(surface, tau, cache_dir=cache_dir) for tau in MEMBRANE_PRESTRESSES], 1)
    # A vertex whose triangles all lie on the clamped rim carries no stress: keep the log finite there.
    floor = 1e-3 * max(float(stresses.mean()), np.finfo(float).tiny)
    return np.log(stresses + floor).astype(np.float32)


def heat_kernel_descriptors(surface: Surface, cache_dir=None) -> np.ndarray:
    """The heat kernel signature at :data:`HKS_TIMES` times, (N, 16) float32.

    :func:`~zernet.operators.spectral.heat_kernel_signature` of the first :data:`HKS_EIGENPAIRS` eigenpairs
    of robust-laplacian's Laplacian (of the mesh, or of the points of a cloud). Why: a patch sees only a few
    radii of the surface, and the patches subtract their centre value, so a model reads nothing of where on
    the surface a vertex is; a foot and a hand look alike to it on a cloud. The signature at large times
    tells them apart (how much heat stays near the point: an extremity keeps more), is intrinsic (the same
    under rigid motions and isometric poses) and scale-free, and is computed on meshes and clouds alike.
    Use it with ``model.input_skip`` so the head sees its values, not only their differences over a patch.
    """
    from zernet.operators.spectral import heat_kernel_signature, laplacian_eigenbasis

    basis = laplacian_eigenbasis(surface, HKS_EIGENPAIRS, cache_dir=cache_dir)
    return heat_kernel_signature(basis, HKS_TIMES)


def _shape_channels(degrees: Sequence[int]) -> int:
    """The "shape" part's channels: the rotation-invariant coefficients of every scale, the boundary distance."""
    return sum(int((orders(n) >= 0).sum()) for n in degrees) + 1


def _shape_part(surface: Surface, operators, cache_dir) -> np.ndarray:
    columns = [shape_descriptors(surface, operator, boundary=False) for operator in operators]
    columns.append(shape_descriptors(surface, operators[0])[:, -1:])
    return np.concatenate(columns, axis=1)


def _curvature_part(surface: Surface, operators, cache_dir) -> np.ndarray:
    return curvature_descriptors(surface, [float(operator.config.r0) for operator in operators])


# The built-in parts (compute_features says what each is).
register_input_part("xyz", 3, lambda surface, operators, cache_dir: default_features(surface))
register_input_part("normals", 3, lambda surface, operators, cache_dir: surface.vertex_normals())
register_input_part("ones", 1, lambda surface, operators, cache_dir: np.ones((surface.n_vertices, 1)))
register_input_part("shape", _shape_channels, _shape_part, reads_operators=True)
register_input_part("curvature", lambda degrees: 1 + len(degrees), _curvature_part, reads_operators=True)
register_input_part(
    "membrane",
    len(MEMBRANE_PRESTRESSES),
    lambda surface, operators, cache_dir: membrane_descriptors(surface, cache_dir),
)
register_input_part("hks", HKS_TIMES, lambda surface, operators, cache_dir: heat_kernel_descriptors(surface, cache_dir))
