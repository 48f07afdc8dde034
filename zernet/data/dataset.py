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

from zernet.geometry import Surface
from zernet.operators import Geometry

__all__ = ["TASKS", "DatasetError", "ShapeRecord", "ShapeDataset", "carve_validation", "as_target"]

TASKS = ("classification", "regression")


class DatasetError(ValueError):
    """A data set that cannot be built: wrong folder layout, missing files, labels that do not match a mesh.

    The message names the file or folder and says what is wrong.
    """


@dataclass(eq=False)
class ShapeRecord:
    """One preprocessed surface, ready for a model.

    Attributes:
        name: the shape's name (file stem or generated name), unique within its data set.
        surface: the area-normalised :class:`~zernet.geometry.surface.Surface` (its ``name`` is the source file).
        features: (N, C_in) float32 model input, by default xyz centred at the area-weighted centroid.
        target: (N,) int64 class per vertex (classification), (N,) float32 value per vertex (regression, in
            area-normalised units), or None when there is no ground truth (prediction on a new surface).
        geometry: :class:`~zernet.operators.batch.Geometry` with one patch operator per configured scale and,
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
        patch_configs: the :class:`~zernet.operators.patch.PatchConfig` list (one per scale) of every record.
        in_channels: number of input feature channels (C_in).
        feature_kind: the feature kind of the records (see :func:`~zernet.data.features.compute_features`).
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
            [self._items[i] for i in indices],
            [self.names[i] for i in indices],
            self.task,
            self.num_classes,
            splits,
            self.patch_configs,
            self.in_channels,
            self.feature_kind,
            self.target_area,
            self.failures,
            self.info,
            self.correspondence,
        )

    def split(self, name: str) -> ShapeDataset:
        """The subset for one split, e.g. ``dataset.split("train")``."""
        if name not in self.splits:
            raise KeyError(f"no split {name!r}; this data set has {sorted(self.splits)}")
        return self.subset(self.splits[name])

    def with_splits(self, splits: dict[str, list[int]]) -> ShapeDataset:
        """The same shapes with other splits (e.g. one leave-one-out fold)."""
        return ShapeDataset(
            self._items,
            self.names,
            self.task,
            self.num_classes,
            splits,
            self.patch_configs,
            self.in_channels,
            self.feature_kind,
            self.target_area,
            self.failures,
            self.info,
            self.correspondence,
        )

    def summary(self) -> str:
        """One line for logs: task, counts, classes, split sizes."""
        sizes = ", ".join(f"{key} {len(value)}" for key, value in self.splits.items())
        classes = f", {self.num_classes} classes" if self.num_classes else ""
        failed = f", {len(self.failures)} failed" if self.failures else ""
        return f"{len(self)} shapes ({self.task}{classes}; {sizes}{failed})"

    def __repr__(self) -> str:
        return f"ShapeDataset({self.summary()})"


def as_target(target, task: str, n_vertices: int, name: str) -> np.ndarray | None:
    """Check a target's length and convert it to the task's dtype (int64 classes / float32 values)."""
    if target is None:
        return None
    target = np.asarray(target)
    if target.ndim == 2 and target.shape[1] == 1:
        target = target[:, 0]
    if target.ndim != 1 or target.shape[0] != n_vertices:
        raise DatasetError(f"{name}: target has shape {target.shape}, expected ({n_vertices},) — one value per vertex")
    if task == "classification":
        if not np.all(np.isfinite(target)) or np.any(target != np.round(target)):
            raise DatasetError(f"{name}: classification labels must be integers")
        return target.astype(np.int64)
    if not np.all(np.isfinite(target)):
        bad = int(np.flatnonzero(~np.isfinite(target))[0])
        raise DatasetError(f"{name}: regression target is not finite at vertex {bad}")
    return target.astype(np.float32)
