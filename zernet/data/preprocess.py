"""Generic preprocessing: shape sources -> validated, area-normalised surfaces with cached patch operators.

Every loader (FAUST, segmentation, regression, synthetic) describes its shapes as :class:`ShapeSource`
objects and hands them to :func:`build_dataset`, which

1. loads each shape (``source.load()`` returns the surface and its per-vertex target),
2. validates it (:func:`~zernet.geometry.validate.validate_surface`), triangulates a point cloud through its
   own points for the front backend (:func:`~zernet.geometry.cloud_mesh.mesh_from_cloud`), and scales it to
   the data set's area
   (:func:`~zernet.geometry.sampling.normalize_area`; a regression target scales with ``area ** target_exponent``),
3. builds one patch operator per :class:`~zernet.operators.patch.PatchConfig` with
   :func:`~zernet.operators.patch.build_patch_operator` (which keeps its own on-disk cache under ``cache_dir``),
4. writes the normalised surface and target to the shape cache (:mod:`zernet.data.cache`) — the marker that
   the shape is done.

Steps 1-4 run in worker processes (:mod:`zernet.data.pool`; ``workers`` 0 or 1 runs them in this process)
with a bounded number of shapes in flight, so memory stays at a few shapes per worker whatever the data set size. A worker returns
only a short status; the records are then read back from the cache. A shape whose cache entry exists is
skipped without loading its file (the entry is read back once to check it; a truncated or corrupt one is
reported by file name and rebuilt). A shape that fails (unreadable file, label mismatch, ...) is recorded
with its name and reason and the others go on; at the end, :func:`build_dataset` raises one
:class:`PreprocessError` listing every failure (``on_error="raise"``, the default, and always when every
shape failed), or leaves the failed shapes out with a :class:`SkippedShapesWarning` (``on_error="skip"``).

Forms (``forms``, :mod:`zernet.data.training_forms`): once the validation shapes are carved from the
training split, the remaining training shapes' forms are made and preprocessed the same way (a second
pass, cached like any shape) and join the training split only.
"""

from __future__ import annotations

import logging
import os
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy.spatial import cKDTree
from tqdm.auto import tqdm

from zernet.data.cache import (
    cached_vertex_count,
    read_cached_target,
    read_shape,
    shape_cache_path,
    usable_cache_entry,
    write_shape,
)
from zernet.data.dataset import DatasetError, ShapeDataset, ShapeRecord, as_target, carve_validation
from zernet.data.features import compute_features, feature_channels, feature_parts
from zernet.data.pool import WORKER_DIED, run_jobs
from zernet.data.source import ShapeSource, file_key
from zernet.data.training_forms import form_sources
from zernet.geometry import Surface, normalize_area, resolve_backend, validate_surface
from zernet.geometry.cloud_mesh import mesh_from_cloud
from zernet.operators import Geometry, PatchConfig, build_patch_operator

__all__ = [
    "ShapeSource",
    "PreprocessError",
    "SkippedShapesWarning",
    "failure_listing",
    "build_dataset",
    "preprocess_shapes",
    "prepare_record",
    "mesh_edge_index",
    "as_patch_configs",
    "file_key",
    "IN_MEMORY_VERTEX_LIMIT",
    "WORKER_DIED",
]


logger = logging.getLogger(__name__)

#: Data sets whose total vertex count times the number of scales is at most this are held in memory;
#: larger ones (FAUST: 100 × 6890) are read back from the cache on each access.
IN_MEMORY_VERTEX_LIMIT = 200_000

# The name under which a regression target travels through normalize_area as a surface field.
_TARGET_FIELD = "__zernet_target__"


class PreprocessError(DatasetError):
    """Shapes failed to load or preprocess: every one with ``on_error="raise"``, or all of them.

    ``failures`` maps each failed shape's name to its reason; ``total`` is the number of shapes tried.
    """

    def __init__(self, message: str, failures: dict[str, str], total: int | None = None):
        super().__init__(message)
        self.failures = dict(failures)
        self.total = len(failures) if total is None else int(total)


class SkippedShapesWarning(RuntimeWarning):
    """Shapes that failed were left out (``on_error="skip"``); the message lists them with their reasons."""


def failure_listing(failures: dict[str, str], total: int) -> str:
    """``"2 of 7 shapes failed to load or preprocess:"`` and one indented ``name: reason`` line per shape."""
    lines = [f"{len(failures)} of {total} shapes failed to load or preprocess:"]
    lines += [f"  {name}: {reason}" for name, reason in failures.items()]
    return "\n".join(lines)


def as_patch_configs(configs) -> list[PatchConfig]:
    """Accept one PatchConfig, a dict, or a list of either; return a list of PatchConfig. An empty list
    builds no patch operators: the data of a model that reads only the mesh graph (FeaStNet)."""
    if configs is None:
        raise DatasetError("no patch configuration given (need at least one PatchConfig, e.g. {'r0': 5.5})")
    if isinstance(configs, (PatchConfig, dict)):
        configs = [configs]
    return [c if isinstance(c, PatchConfig) else PatchConfig(**dict(c)) for c in configs]


def mesh_edge_index(surface: Surface, k_cloud: int = 8) -> torch.Tensor:
    """(2, E) int64 edges in both directions, for graph baselines (FeaStNet).

    Meshes: every mesh edge once in each direction. Point clouds: the symmetrised k-nearest-neighbour graph
    (k = ``k_cloud``), since a cloud has no edges of its own.
    """
    if surface.faces is not None:
        edges = surface.edges()  # (E, 2) unique undirected pairs
    else:
        k = min(k_cloud, surface.n_vertices - 1)
        _, neighbours = cKDTree(surface.vertices).query(surface.vertices, k=k + 1)
        rows = np.repeat(np.arange(surface.n_vertices), k)
        edges = np.unique(np.sort(np.stack([rows, neighbours[:, 1:].reshape(-1)], axis=1), axis=1), axis=0)
    both = np.concatenate([edges, edges[:, ::-1]], axis=0).T
    return torch.from_numpy(np.ascontiguousarray(both, dtype=np.int64))


# ------------------------------------------------------------------------------------------ per-shape work
def _normalise(surface: Surface, target, target_area: float | None, target_exponent: float, repair: bool, configs):
    """Validate, triangulate a point cloud for the front backend, scale to ``target_area`` (None: keep),
    scale the target with its area exponent."""
    surface = validate_surface(surface, repair=repair)
    if surface.is_point_cloud and any(resolve_backend(surface, c.backend) == "front" for c in configs):
        # Through its own points (same vertices): normals, area and patches then come from triangles,
        # exactly as for a mesh, so a model trained on meshes reads the cloud's features the same way.
        surface = mesh_from_cloud(surface)
    if target_area is None:
        return surface, (None if target is None else np.asarray(target)), 1.0
    carry = target is not None and target_exponent != 0
    if carry:
        target = np.asarray(target, dtype=np.float64)
        if target.shape[0] != surface.n_vertices:
            raise DatasetError(
                f"{surface.name}: target has {target.shape[0]} values but the surface has {surface.n_vertices} vertices"
            )
        surface = surface.with_fields({_TARGET_FIELD: target})
    scaled, scale = normalize_area(surface, target_area, {_TARGET_FIELD: target_exponent} if carry else None)
    if carry:
        target = scaled.fields[_TARGET_FIELD]
        fields = {k: v for k, v in scaled.fields.items() if k != _TARGET_FIELD}
        scaled = Surface(scaled.vertices, scaled.faces, scaled.normals, fields, scaled.name)
    return scaled, target, scale


def _prepare_one(job: tuple) -> tuple[str, str | None]:
    """Worker: load, normalise, build every operator, write the cache entry. Returns (name, error or None)."""
    source, configs, cache_dir, target_area, repair, cache_path = job
    try:
        surface, target = source.load()
        surface, target, scale = _normalise(surface, target, target_area, source.target_exponent, repair, configs)
        if target is not None and np.asarray(target).shape[0] != surface.n_vertices:
            raise DatasetError(
                f"{surface.name}: target has {np.asarray(target).shape[0]} values but the surface "
                f"has {surface.n_vertices} vertices"
            )
        for config in configs:
            build_patch_operator(surface, config, cache_dir=cache_dir)
        if cache_path is not None:
            write_shape(cache_path, surface, target, scale)
        return source.name, None
    except Exception as error:  # reported by name; the other shapes go on
        message = str(error) or type(error).__name__
        if not isinstance(error, (ValueError, OSError)):
            message = f"{type(error).__name__}: {message}"
        return source.name, message


def preprocess_shapes(
    sources: Sequence[ShapeSource],
    patch_configs,
    cache_dir: str | os.PathLike,
    target_area: float | None,
    workers: int | None = None,
    repair: bool = False,
    progress: bool = True,
    max_in_flight: int | None = None,
    description: str = "preprocess",
) -> dict[str, str]:
    """Preprocess every source into ``cache_dir`` (see the module docstring). Returns {name: failure reason}.

    workers: processes to use; None = number of CPUs (at most the number of shapes to do); 0 or 1 = in this
        process. Pool workers start from a fresh interpreter (forkserver/spawn; see
        :func:`~zernet.data.pool.pool_context`), so a script calling this needs the usual
        ``if __name__ == "__main__":`` guard. If the pool breaks, the remaining shapes are processed one at a
        time in fresh workers with a warning.
    max_in_flight: shapes submitted but not finished at any time (default 2 per worker), which bounds memory.
    description: the progress bar's label.
    """
    configs = as_patch_configs(patch_configs)
    cache_dir = Path(cache_dir)
    cache_dir.mkdir(parents=True, exist_ok=True)
    names = [s.name for s in sources]
    if len(set(names)) != len(names):
        raise DatasetError(
            f"shape names must be unique; repeated: {sorted({n for n in names if names.count(n) > 1})[:5]}"
        )

    jobs = {}
    for source in sources:
        path = shape_cache_path(cache_dir, source, target_area, configs, repair)
        if path is None or not usable_cache_entry(path):
            jobs[source.name] = (source, configs, str(cache_dir), target_area, repair, path)
    if len(jobs) < len(sources):
        logger.info(
            "preprocess: %d of %d shapes already cached, %d to do", len(sources) - len(jobs), len(sources), len(jobs)
        )
    failures: dict[str, str] = {}
    bar = tqdm(
        total=len(sources),
        initial=len(sources) - len(jobs),
        desc=description,
        unit="shape",
        disable=not progress or not jobs,
        leave=False,
    )

    def record(name: str, error: str | None) -> None:
        if error is not None:
            failures[name] = error
            logger.info("preprocessing %s failed: %s", name, error)
            bar.set_postfix(failed=len(failures))
        bar.update(1)

    if workers is None:
        workers = os.cpu_count() or 1
    workers = max(0, min(int(workers), len(jobs)))
    try:
        run_jobs(_prepare_one, jobs, workers, max_in_flight or 2 * workers, record)
    finally:
        bar.close()
    return failures


def _make_record(
    surface: Surface, target, scale: float, name: str, configs, cache_dir, task: str, feature_kind: str
) -> ShapeRecord:
    operators = [build_patch_operator(surface, config, cache_dir=cache_dir) for config in configs]
    geometry = Geometry(operators=operators, edge_index=mesh_edge_index(surface))
    return ShapeRecord(
        name=name,
        surface=surface,
        features=compute_features(surface, feature_kind, operators, cache_dir=cache_dir),
        target=as_target(target, task, surface.n_vertices, surface.name),
        geometry=geometry,
        scale=scale,
    )


class _CachedRecord:
    """Picklable loader of one record from the shape cache (used for data sets not held in memory)."""

    def __init__(self, path: Path, name: str, configs, cache_dir: str, task: str, feature_kind: str):
        self.path, self.name, self.configs = path, name, configs
        self.cache_dir, self.task, self.feature_kind = cache_dir, task, feature_kind

    def target(self) -> np.ndarray | None:
        """Only the target, read from the cache file (no operators built)."""
        target, n_vertices = read_cached_target(self.path)
        return as_target(target, self.task, n_vertices, self.name)

    def __call__(self) -> ShapeRecord:
        surface, target, scale = read_shape(self.path)
        return _make_record(
            surface, target, scale, self.name, self.configs, self.cache_dir, self.task, self.feature_kind
        )


def prepare_record(
    surface: Surface,
    patch_configs,
    cache_dir: str | os.PathLike | None,
    target_area: float | None,
    target=None,
    task: str = "regression",
    feature_kind: str = "xyz",
    target_exponent: float = 0.0,
    repair: bool = False,
    name: str | None = None,
) -> ShapeRecord:
    """Preprocess one surface in this process (e.g. a user's mesh for ``zernet predict``).

    The same steps as a data set shape: validate, normalise to ``target_area`` (use the training data set's
    ``target_area`` so patch radii mean the same), build operators (cached under ``cache_dir`` when given).
    Returns a :class:`ShapeRecord` whose ``scale`` maps predictions back (see :class:`ShapeRecord`).
    """
    configs = as_patch_configs(patch_configs)
    surface, target, scale = _normalise(surface, target, target_area, target_exponent, repair, configs)
    name = name or Path(surface.name).stem
    return _make_record(
        surface, target, scale, name, configs, None if cache_dir is None else str(cache_dir), task, feature_kind
    )


def build_dataset(
    sources: Sequence[ShapeSource],
    patch_configs,
    cache_dir: str | os.PathLike,
    target_area: float | None,
    task: str,
    num_classes: int | None,
    split_names: dict[str, Sequence[str]],
    n_val: int | float = 0,
    seed: int = 0,
    feature_kind: str = "xyz",
    workers: int | None = None,
    on_error: str = "raise",
    repair: bool = False,
    progress: bool = True,
    in_memory: bool | None = None,
    info: dict[str, Any] | None = None,
    correspondence: bool = False,
    forms: dict[str, float] | None = None,
) -> ShapeDataset:
    """Preprocess ``sources`` and assemble the :class:`ShapeDataset`.

    Args:
        sources: one :class:`ShapeSource` per shape; their order is the data set's order.
        patch_configs: PatchConfig (or dicts), one per scale.
        cache_dir: folder for the shape cache and the patch operators' cache.
        target_area: area every surface is scaled to (None: keep the file's scale), or a
            :class:`~zernet.geometry.FixedScale` factor applied to every surface instead.
        task, num_classes: see :class:`ShapeDataset`.
        split_names: {"train": names, "test": names, ...}; a "val" split is carved from "train"
            (``n_val`` shapes or a fraction, seeded by ``seed``) unless split_names already has one.
            Shapes that failed are dropped from every split.
        feature_kind: parts of :data:`~zernet.data.features.FEATURE_PARTS` joined by '+'.
        workers, repair, progress: see :func:`preprocess_shapes`.
        on_error: ``"raise"``: if any shape fails, raise one :class:`PreprocessError` listing every failure
            (all shapes are tried first); ``"skip"``: leave failed shapes out with a
            :class:`SkippedShapesWarning` (``dataset.failures`` lists them); an error if every shape failed.
        in_memory: hold every record in memory; None decides by size (:data:`IN_MEMORY_VERTEX_LIMIT`).
        info: extra description stored on the data set.
        correspondence: mark the data set as template correspondence (class = vertex index).
        forms: {form name: copies per training shape} of the training shapes (not the validation ones)
            added to the training split, drawn with ``seed`` (:mod:`zernet.data.training_forms`); what was
            made is counted in ``info["forms"]``.
    """
    feature_parts(feature_kind)  # an unknown kind fails here, before any preprocessing
    if not sources:
        raise DatasetError("no shapes to preprocess")
    if on_error not in ("raise", "skip"):
        raise DatasetError(f"on_error must be 'raise' or 'skip', got {on_error!r}")
    configs = as_patch_configs(patch_configs)
    cache_dir = Path(cache_dir)
    failures = preprocess_shapes(
        sources, configs, cache_dir, target_area, workers=workers, repair=repair, progress=progress
    )
    _report_failures(failures, len(sources), on_error)

    kept = [s for s in sources if s.name not in failures]
    loaders = [_record_loader(source, configs, cache_dir, target_area, task, feature_kind, repair) for source in kept]
    names = [s.name for s in kept]
    splits = _index_splits(split_names, names, {s.name for s in sources}, n_val, seed)
    if forms:
        made = form_sources([kept[i] for i in splits["train"]], forms, seed)
        every_form = [source for sources in made.values() for source in sources]
        form_failures = preprocess_shapes(
            every_form, configs, cache_dir, target_area, workers, repair, progress, description="forms"
        )
        _report_failures(form_failures, len(every_form), on_error)
        failures.update(form_failures)
        made = {form: [s for s in sources if s.name not in form_failures] for form, sources in made.items()}
        for sources in made.values():
            splits["train"] += range(len(names), len(names) + len(sources))
            loaders += [_record_loader(s, configs, cache_dir, target_area, task, feature_kind, repair) for s in sources]
            names += [s.name for s in sources]
        info = {**(info or {}), "forms": {form: len(sources) for form, sources in made.items()}}

    if in_memory is None:
        in_memory = _estimate_vertices(loaders) * len(configs) <= IN_MEMORY_VERTEX_LIMIT
    if in_memory:
        loaders = [item if isinstance(item, ShapeRecord) else item() for item in loaders]
    in_channels = feature_channels(feature_kind, [c.n_max for c in configs] or 5)
    return ShapeDataset(
        loaders,
        names,
        task,
        num_classes,
        splits,
        configs,
        in_channels,
        feature_kind,
        target_area,
        failures,
        info,
        correspondence,
    )


def _report_failures(failures: dict[str, str], total: int, on_error: str) -> None:
    """Raise one :class:`PreprocessError` listing ``failures`` (``on_error="raise"``, or all ``total`` shapes
    failed), or warn that they are left out (``"skip"``)."""
    if not failures:
        return
    message = failure_listing(failures, total)
    if on_error == "raise" or len(failures) == total:
        hint = "" if len(failures) == total else "\n(on_error='skip' leaves them out)"
        raise PreprocessError(message + hint, failures, total)
    warnings.warn(message + "\n(left out: on_error='skip')", SkippedShapesWarning, stacklevel=3)


def _record_loader(
    source: ShapeSource, configs, cache_dir: Path, target_area: float | None, task: str, feature_kind: str, repair: bool
) -> ShapeRecord | _CachedRecord:
    """The record of a preprocessed shape, or its loader from the shape cache."""
    path = shape_cache_path(cache_dir, source, target_area, configs, repair)
    if path is not None:
        return _CachedRecord(path, source.name, configs, str(cache_dir), task, feature_kind)
    # No content key: nothing on disk to reload from, so this shape is built here and kept in memory.
    surface, target = source.load()
    surface, target, scale = _normalise(surface, target, target_area, source.target_exponent, repair, configs)
    return _make_record(surface, target, scale, source.name, configs, str(cache_dir), task, feature_kind)


def _index_splits(
    split_names: dict[str, Sequence[str]], kept: list[str], every_name: set[str], n_val: int | float, seed: int
) -> dict[str, list[int]]:
    """Splits by name -> index lists into the kept shapes, with "val" carved from "train" when not given."""
    position = {name: i for i, name in enumerate(kept)}
    unknown = sorted({n for split in split_names.values() for n in split} - every_name)
    if unknown:
        raise DatasetError(f"splits name shapes that are not in the data set: {unknown[:5]}")
    splits = {key: sorted(position[n] for n in value if n in position) for key, value in split_names.items()}
    if "val" not in splits:
        splits["train"], splits["val"] = carve_validation(splits.get("train", []), n_val, seed)
    splits.setdefault("test", [])
    return splits


def _estimate_vertices(loaders) -> int:
    """Total vertex count of the data set (reads only the vertex arrays of the cache files)."""
    total = 0
    for item in loaders:
        if isinstance(item, ShapeRecord):
            total += item.n_vertices
        else:
            total += cached_vertex_count(item.path)
    return total
