"""Data set containers: :class:`ShapeRecord` (one preprocessed surface) and :class:`ShapeDataset`.

A data set is a sequence of records plus what training needs to know about it: the task
(``"classification"`` or ``"regression"``), the number of classes, the shape names and the splits.
The splits are index lists into the data set: ``"train"``, ``"val"`` (carved from the training shapes with a
seeded shuffle — never from the test shapes, so model selection never sees them) and ``"test"``.

Records are either held in memory or loaded from the preprocessing cache each time they are indexed (large
data sets such as FAUST: one 6890-vertex patch operator takes a few hundred MB, so 100 of them do not fit).
Both behave identically; see :class:`ShapeDataset`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse
from scipy.spatial import cKDTree

from zernet.membrane import membrane_stress
from zernet.nn.geometry import Geometry
from zernet.surface import Surface
from zernet.zernike import harmonic_pairs, index_to_nm, orders

__all__ = [
    "TASKS",
    "FEATURE_PARTS",
    "MEMBRANE_PRESTRESSES",
    "feature_parts",
    "membrane_descriptors",
    "ShapeRecord",
    "ShapeDataset",
    "default_features",
    "compute_features",
    "feature_channels",
    "shape_descriptors",
    "curvature_descriptors",
    "carve_validation",
    "DatasetError",
]

TASKS = ("classification", "regression")

#: Parts a feature kind is made of, with their channel counts (None: depends on the patch settings, see
#: :func:`feature_channels`). A kind joins parts with "+", e.g. ``"xyz+normals"`` or
#: ``"shape+curvature+membrane"``; the channels follow in that order.
FEATURE_PARTS = {"xyz": 3, "normals": 3, "ones": 1, "shape": None, "curvature": None, "membrane": 3}

#: Pre-tensions of the :func:`~zernet.membrane.membrane_stress` channels of the "membrane" feature part.
MEMBRANE_PRESTRESSES = (0.01, 0.02, 0.04)

#: Distance to the boundary, in units of r0, beyond which the boundary feature saturates.
BOUNDARY_SATURATION = 3.0


class DatasetError(ValueError):
    """A data set that cannot be built: wrong folder layout, missing files, labels that do not match a mesh.

    The message names the file or folder and says what is wrong.
    """


@dataclass(eq=False)
class ShapeRecord:
    """One preprocessed surface, ready for a model.

    Attributes:
        name: the shape's name (file stem or generated name), unique within its data set.
        surface: the area-normalised :class:`~zernet.surface.Surface` (its ``name`` is the source file).
        features: (N, C_in) float32 model input, by default xyz centred at the area-weighted centroid.
        target: (N,) int64 class per vertex (classification), (N,) float32 value per vertex (regression, in
            area-normalised units), or None when there is no ground truth (prediction on a new surface).
        geometry: :class:`~zernet.nn.geometry.Geometry` with one patch operator per configured scale and,
            for meshes, ``edge_index`` (2, E) of the mesh edges in both directions (for graph baselines).
        scale: linear factor applied to the positions by the area normalisation (new = centroid + scale·(old
            − centroid)). A regression target with area exponent e was multiplied by ``scale ** (2 e)``;
            divide a prediction by that to return to the file's units.
    """

    name: str
    surface: Surface
    features: np.ndarray
    target: np.ndarray | None
    geometry: Geometry
    scale: float = 1.0

    @property
    def n_vertices(self) -> int:
        return int(self.features.shape[0])


def default_features(surface: Surface) -> np.ndarray:
    """The default model input: vertex positions centred at the area-weighted centroid, (N, 3) float32.

    The centroid is ``Σ_i a_i x_i / Σ_i a_i`` with ``a_i`` the per-vertex areas of
    :meth:`Surface.vertex_areas` (a third of the incident triangle areas; estimated cell areas for point
    clouds), i.e. the centroid of the surface as a thin shell, not of its vertex set: it does not move when
    one region is meshed more densely than another. It is the point about which
    :func:`~zernet.surface.normalize_area` scales, so centring does not depend on the normalisation.
    No rotation is removed: the features are as rotation-dependent as the surface's placement.
    """
    weights = surface.vertex_areas()
    centroid = weights @ surface.vertices / weights.sum()
    return (surface.vertices - centroid).astype(np.float32)


def feature_parts(kind: str) -> list[str]:
    """The :data:`FEATURE_PARTS` of feature kind ``kind`` ("+"-joined), in order; DatasetError if unknown."""
    parts = str(kind).split("+")
    unknown = [part for part in parts if part not in FEATURE_PARTS]
    if unknown or len(set(parts)) != len(parts):
        raise DatasetError(f"unknown feature kind {kind!r}: join distinct parts of {sorted(FEATURE_PARTS)} "
                           "with '+', e.g. 'xyz+normals' or 'shape+curvature+membrane'")
    return parts


def feature_channels(kind: str, n_max=5) -> int:
    """Number of input channels of feature ``kind``; ``n_max``: the degree of each patch scale (int or list)."""
    degrees = [n_max] if isinstance(n_max, int) else list(n_max)
    channels = 0
    for part in feature_parts(kind):
        if part == "shape":
            channels += sum(int((orders(n) >= 0).sum()) for n in degrees) + 1
        elif part == "curvature":
            channels += 1 + len(degrees)
        else:
            channels += FEATURE_PARTS[part]
    return channels


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


def compute_features(surface: Surface, kind: str = "xyz", operators=None, cache_dir=None) -> np.ndarray:
    """Model input of feature kind ``kind``, (N, C) float32: its :data:`FEATURE_PARTS` side by side.

    - ``"xyz"``: :func:`default_features` (3);
    - ``"normals"``: unit vertex normals (3);
    - ``"ones"``: a constant 1 per vertex (the model then sees geometry only through the patch operators'
      frames and sampling, useful as an ablation);
    - ``"shape"``: :func:`shape_descriptors` at every patch scale, then the boundary distance in units of the
      first scale's r0 (rotation- and translation-invariant);
    - ``"curvature"``: :func:`curvature_descriptors` at the patch scales' radii;
    - ``"membrane"``: log of :func:`~zernet.membrane.membrane_stress` at each of
      :data:`MEMBRANE_PRESTRESSES` (meshes only; cached in ``cache_dir`` when given).

    ``operators``: the surface's patch operators, one per scale (needed by "shape" and "curvature").
    """
    columns = []
    for part in feature_parts(kind):
        if part in ("shape", "curvature") and not operators:
            raise DatasetError(f"feature part {part!r} of {kind!r} needs the surface's patch operators")
        if part == "xyz":
            columns.append(default_features(surface))
        elif part == "normals":
            columns.append(surface.vertex_normals().astype(np.float32))
        elif part == "ones":
            columns.append(np.ones((surface.n_vertices, 1), dtype=np.float32))
        elif part == "shape":
            columns += [shape_descriptors(surface, op, boundary=False) for op in operators]
            columns.append(shape_descriptors(surface, operators[0])[:, -1:])
        elif part == "curvature":
            columns.append(curvature_descriptors(surface, [float(op.config.r0) for op in operators]))
        elif part == "membrane":
            columns.append(membrane_descriptors(surface, cache_dir))
    return np.concatenate(columns, axis=1).astype(np.float32)


def membrane_descriptors(surface: Surface, cache_dir=None) -> np.ndarray:
    """log of the membrane stress under unit inner pressure at each :data:`MEMBRANE_PRESTRESSES`, (N, 3).

    Why: for stress targets this solves the wall's equilibrium (see :mod:`zernet.membrane`) instead of asking
    the network to learn it from a few shapes. The log makes a scaled stress a shifted feature. A point
    cloud has no wall: DatasetError naming the shape.
    """
    if surface.is_point_cloud:
        raise DatasetError(f"{surface.name}: feature part 'membrane' needs a triangle mesh, got a point cloud")
    stresses = np.stack([membrane_stress(surface, tau, cache_dir=cache_dir) for tau in MEMBRANE_PRESTRESSES], 1)
    # A vertex whose triangles all lie on the clamped rim carries no stress: keep the log finite there.
    floor = 1e-3 * max(float(stresses.mean()), np.finfo(float).tiny)
    return np.log(stresses + floor).astype(np.float32)


def carve_validation(train: Sequence[int], n_val: int | float, seed: int) -> tuple[list[int], list[int]]:
    """Split training indices into (train, val) with a seeded shuffle.

    n_val: a count (int >= 0) or a fraction of the training shapes (0 < float < 1, rounded, at least 1).
    At least one shape always stays in train, so n_val is capped at ``len(train) - 1``.
    Returns two sorted index lists; the same (train, n_val, seed) always gives the same split.
    """
    train = sorted(int(i) for i in train)
    if isinstance(n_val, float) and 0 < n_val < 1:
        count = max(1, int(round(n_val * len(train))))
    else:
        count = int(n_val)
        if count < 0 or count != n_val:
            raise DatasetError(f"n_val must be a non-negative count or a fraction in (0, 1), got {n_val!r}")
    count = max(0, min(count, len(train) - 1))
    order = np.random.default_rng(seed).permutation(len(train))
    val = sorted(train[i] for i in order[:count])
    return [i for i in train if i not in set(val)], val


class ShapeDataset(Sequence[ShapeRecord]):
    """A sequence of :class:`ShapeRecord` with its task, classes, names and splits.

    Attributes:
        task: ``"classification"`` or ``"regression"``.
        num_classes: number of classes (classification) or None (regression).
        names: shape names, in index order.
        splits: {"train": [...], "val": [...], "test": [...]} index lists (more keys are allowed).
        patch_configs: the :class:`~zernet.patches.PatchConfig` list (one per scale) of every record.
        in_channels: number of input feature channels (C_in).
        feature_kind: the feature kind of the records (see :func:`compute_features`).
        target_area: the area every surface was normalised to.
        failures: {name: reason} of shapes that could not be preprocessed and are left out.
        info: free-form description (source folder, label base, ...), JSON-serialisable. Regression data
            sets say their target's area exponent as ``info["target_exponent"]``, so that predictions on a
            new surface are returned in its own units.
        correspondence: True when the class of a vertex is a vertex index of a shared template (FAUST):
            evaluation then measures geodesic errors on the test shape.

    Indexing with an int returns a record; ``subset(indices)`` and ``split(name)`` return new data sets that
    share the same records or loaders.

    Records come from ``items``: each item is either a ready :class:`ShapeRecord` (held in memory) or a
    zero-argument callable returning one (loaded from the cache on each access, so memory stays bounded by
    what the caller keeps).
    """

    def __init__(
        self,
        items: Sequence[ShapeRecord | Callable[[], ShapeRecord]],
        names: Sequence[str],
        task: str,
        num_classes: int | None,
        splits: dict[str, list[int]],
        patch_configs: Sequence[Any],
        in_channels: int,
        feature_kind: str = "xyz",
        target_area: float | None = None,
        failures: dict[str, str] | None = None,
        info: dict[str, Any] | None = None,
        correspondence: bool = False,
    ):
        if task not in TASKS:
            raise DatasetError(f"task must be one of {TASKS}, got {task!r}")
        if task == "classification" and (num_classes is None or num_classes < 1):
            raise DatasetError(f"a classification data set needs num_classes >= 1, got {num_classes!r}")
        if len(items) != len(names):
            raise DatasetError(f"{len(items)} records but {len(names)} names")
        if len(set(names)) != len(names):
            duplicated = sorted({n for n in names if list(names).count(n) > 1})
            raise DatasetError(f"shape names must be unique; repeated: {duplicated[:5]}")
        for key, indices in splits.items():
            bad = [i for i in indices if not 0 <= i < len(items)]
            if bad:
                raise DatasetError(f"split {key!r} refers to shapes {bad[:5]} outside 0..{len(items) - 1}")
        overlap = set(splits.get("test", ())) & (set(splits.get("train", ())) | set(splits.get("val", ())))
        if overlap:
            raise DatasetError(f"test shapes {sorted(overlap)[:5]} are also in train/val")
        self._items = list(items)
        self.names = list(names)
        self.task = task
        self.num_classes = None if task == "regression" else int(num_classes)
        self.splits = {key: [int(i) for i in value] for key, value in splits.items()}
        self.patch_configs = list(patch_configs)
        self.in_channels = int(in_channels)
        self.feature_kind = feature_kind
        self.target_area = target_area
        self.failures = dict(failures or {})
        self.info = dict(info or {})
        self.correspondence = bool(correspondence)

    # ------------------------------------------------------------------ sequence protocol
    def __len__(self) -> int:
        return len(self._items)

    def __getitem__(self, index):
        if isinstance(index, slice):
            return self.subset(range(len(self))[index])
        if isinstance(index, str):
            index = self.index(index)
        item = self._items[index]
        return item if isinstance(item, ShapeRecord) else item()

    def target(self, index: int) -> np.ndarray | None:
        """The target of shape ``index`` without building its operators (cheap for cached data sets)."""
        item = self._items[index]
        if isinstance(item, ShapeRecord):
            return item.target
        read_target = getattr(item, "target", None)
        return read_target() if read_target is not None else item().target

    def index(self, name: str) -> int:
        """Position of the shape called ``name``."""
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(f"no shape named {name!r} in this data set ({len(self)} shapes)") from None

    @property
    def in_memory(self) -> bool:
        """True when every record is held in memory (no cache reads on access)."""
        return all(isinstance(item, ShapeRecord) for item in self._items)

    # ------------------------------------------------------------------ views
    def subset(self, indices: Sequence[int]) -> ShapeDataset:
        """A data set of the shapes at ``indices`` (in that order), sharing records/loaders.

        Splits are carried over: each split keeps the chosen shapes it contained, renumbered to positions in
        the subset.
        """
        indices = [int(i) for i in indices]
        position = {old: new for new, old in enumerate(indices)}
        splits = {key: [position[i] for i in value if i in position] for key, value in self.splits.items()}
        return ShapeDataset(
            [self._items[i] for i in indices], [self.names[i] for i in indices], self.task, self.num_classes,
            splits, self.patch_configs, self.in_channels, self.feature_kind, self.target_area, self.failures,
            self.info, self.correspondence,
        )

    def split(self, name: str) -> ShapeDataset:
        """The subset for one split, e.g. ``dataset.split("train")``."""
        if name not in self.splits:
            raise KeyError(f"no split {name!r}; this data set has {sorted(self.splits)}")
        return self.subset(self.splits[name])

    def with_splits(self, splits: dict[str, list[int]]) -> ShapeDataset:
        """The same shapes with other splits (e.g. one leave-one-out fold)."""
        return ShapeDataset(
            self._items, self.names, self.task, self.num_classes, splits, self.patch_configs, self.in_channels,
            self.feature_kind, self.target_area, self.failures, self.info, self.correspondence,
        )

    def summary(self) -> str:
        """One line for logs: task, counts, classes, split sizes."""
        sizes = ", ".join(f"{key} {len(value)}" for key, value in self.splits.items())
        classes = f", {self.num_classes} classes" if self.num_classes else ""
        failed = f", {len(self.failures)} failed" if self.failures else ""
        return f"{len(self)} shapes ({self.task}{classes}; {sizes}{failed})"

    def __repr__(self) -> str:
        return f"ShapeDataset({self.summary()})"


def _as_target(target, task: str, n_vertices: int, name: str) -> np.ndarray | None:
    """Check a target's length and convert it to the task's dtype (int64 classes / float32 values)."""
    if target is None:
        return None
    target = np.asarray(target)
    if target.ndim == 2 and target.shape[1] == 1:
        target = target[:, 0]
    if target.ndim != 1 or target.shape[0] != n_vertices:
        raise DatasetError(f"{name}: target has shape {target.shape}, expected ({n_vertices},) — one value "
                           f"per vertex")
    if task == "classification":
        if not np.all(np.isfinite(target)) or np.any(target != np.round(target)):
            raise DatasetError(f"{name}: classification labels must be integers")
        return target.astype(np.int64)
    if not np.all(np.isfinite(target)):
        bad = int(np.flatnonzero(~np.isfinite(target))[0])
        raise DatasetError(f"{name}: regression target is not finite at vertex {bad}")
    return target.astype(np.float32)

