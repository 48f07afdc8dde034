"""Generic preprocessing: shape sources -> validated, area-normalised surfaces with cached patch operators.

Every loader (FAUST, segmentation, regression, synthetic) describes its shapes as :class:`ShapeSource`
objects and hands them to :func:`build_dataset`, which

1. loads each shape (``source.load()`` returns the surface and its per-vertex target),
2. validates it (:func:`~zernet.surface.validate_surface`) and scales it to the data set's area
   (:func:`~zernet.surface.normalize_area`; a regression target scales with ``area ** target_exponent``),
3. builds one patch operator per :class:`~zernet.patches.PatchConfig` with
   :func:`~zernet.patches.build_patch_operator` (which keeps its own on-disk cache under ``cache_dir``),
4. writes the normalised surface and target to ``cache_dir/shapes/`` — the marker that the shape is done.

Steps 1-4 run in worker processes (``workers``; 0 or 1 runs them in this process) with a bounded number of
shapes in flight, so memory stays at a few shapes per worker whatever the data set size. A worker returns
only a short status; the records are then read back from the cache. A shape whose cache entry exists is
skipped without loading its file (the entry is read back once to check it; a truncated or corrupt one is
reported by file name and rebuilt). A shape that fails (unreadable file, label mismatch, ...) is reported
with its name and reason and the others go on; :class:`PreprocessError` is raised at the end only when
every shape failed or when ``strict=True``.
"""

from __future__ import annotations

import hashlib
import json
import logging
import multiprocessing
import os
import re
import sys
import warnings
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass, is_dataclass, asdict
from pathlib import Path
from typing import Any

import numpy as np
import torch

from zernet.data.base import (
    DatasetError,
    ShapeDataset,
    ShapeRecord,
    _as_target,
    carve_validation,
    compute_features,
    feature_channels,
    feature_parts,
)
from zernet.io_utils import atomic_write_bytes
from zernet.nn.geometry import Geometry
from zernet.patches import PatchConfig, build_patch_operator
from zernet.surface import Surface, normalize_area, validate_surface

__all__ = [
    "ShapeSource",
    "PreprocessError",
    "build_dataset",
    "preprocess_shapes",
    "prepare_record",
    "mesh_edge_index",
    "as_patch_configs",
    "file_key",
    "IN_MEMORY_VERTEX_LIMIT",
]

logger = logging.getLogger(__name__)

#: Data sets whose total vertex count times the number of scales is at most this are held in memory;
#: larger ones (FAUST: 100 × 6890) are read back from the cache on each access.
IN_MEMORY_VERTEX_LIMIT = 200_000

# Bump when the content of the shape cache files changes, so old entries are not misread.
_CACHE_FORMAT = "zernet-shape-1"
# The name under which a regression target travels through normalize_area as a surface field.
_TARGET_FIELD = "__zernet_target__"


class PreprocessError(RuntimeError):
    """Preprocessing failed for every shape, or for any shape with ``strict=True``. Lists name and reason."""

    def __init__(self, message: str, failures: dict[str, str]):
        super().__init__(message)
        self.failures = dict(failures)


@dataclass(frozen=True)
class ShapeSource:
    """How to obtain one shape and its ground truth.

    Attributes:
        name: unique name within the data set (used in splits, messages and the cache file name).
        load: zero-argument callable returning ``(surface, target)``; ``target`` is an (N,) per-vertex array
            or None. It runs in a worker process, so it must be picklable: a module-level function or a
            ``functools.partial`` of one — never a lambda or a closure. It should raise
            :class:`~zernet.surface.SurfaceError` / :class:`~zernet.data.base.DatasetError` with a clear
            message for a bad file.
        key: a string that changes whenever the shape's content would change (e.g. file paths with sizes
            and modification times, or generator parameters), used to skip already cached shapes without
            loading them. None disables the skip (operators are still cached by geometry hash).
        target_exponent: area exponent of a regression target: the target is multiplied by
            ``(target_area / area) ** target_exponent`` when the surface is normalised (0.5 for wall stress,
            -0.5 for a curvature, 0 for labels and dimensionless values).
    """

    name: str
    load: Callable[[], tuple[Surface, np.ndarray | None]]
    key: str | None = None
    target_exponent: float = 0.0


def file_key(*paths: str | os.PathLike) -> str:
    """Content key for file-based sources: absolute path, size and modification time of each file."""
    parts = []
    for path in paths:
        stat = os.stat(path)
        parts.append(f"{os.path.abspath(path)}|{stat.st_size}|{stat.st_mtime_ns}")
    return ";".join(parts)


def as_patch_configs(configs) -> list[PatchConfig]:
    """Accept one PatchConfig, a dict, or a list of either; return a non-empty list of PatchConfig."""
    if configs is None:
        raise DatasetError("no patch configuration given (need at least one PatchConfig, e.g. {'r0': 5.5})")
    if isinstance(configs, (PatchConfig, dict)):
        configs = [configs]
    result = [c if isinstance(c, PatchConfig) else PatchConfig(**dict(c)) for c in configs]
    if not result:
        raise DatasetError("no patch configuration given (need at least one PatchConfig, e.g. {'r0': 5.5})")
    return result


def mesh_edge_index(surface: Surface, k_cloud: int = 8) -> torch.Tensor:
    """(2, E) int64 edges in both directions, for graph baselines (FeaStNet).

    Meshes: every mesh edge once in each direction. Point clouds: the symmetrised k-nearest-neighbour graph
    (k = ``k_cloud``), since a cloud has no edges of its own.
    """
    if surface.faces is not None:
        edges = surface.edges()  # (E, 2) unique undirected pairs
    else:
        from scipy.spatial import cKDTree

        k = min(k_cloud, surface.n_vertices - 1)
        _, neighbours = cKDTree(surface.vertices).query(surface.vertices, k=k + 1)
        rows = np.repeat(np.arange(surface.n_vertices), k)
        edges = np.unique(np.sort(np.stack([rows, neighbours[:, 1:].reshape(-1)], axis=1), axis=1), axis=0)
    both = np.concatenate([edges, edges[:, ::-1]], axis=0).T
    return torch.from_numpy(np.ascontiguousarray(both, dtype=np.int64))


# --------------------------------------------------------------------------------------------- cache entries
def _config_fingerprint(config: PatchConfig) -> dict:
    return asdict(config) if is_dataclass(config) else dict(vars(config))


def _cache_path(cache_dir: Path, source: ShapeSource, target_area: float | None, configs, repair: bool) -> Path | None:
    """Cache file of one shape, or None when the source has no content key."""
    if source.key is None:
        return None
    description = json.dumps(
        {
            "format": _CACHE_FORMAT,
            "key": source.key,
            "area": target_area,
            "exponent": source.target_exponent,
            "repair": repair,
            "configs": [_config_fingerprint(c) for c in configs],
        },
        sort_keys=True,
        default=str,
    )
    digest = hashlib.sha256(description.encode()).hexdigest()[:20]
    safe = re.sub(r"[^A-Za-z0-9_.-]+", "_", source.name)[:60]
    return cache_dir / "shapes" / f"{safe}-{digest}.npz"


def _write_shape(path: Path, surface: Surface, target: np.ndarray | None, scale: float) -> None:
    import io

    buffer = io.BytesIO()
    arrays = {"vertices": surface.vertices, "scale": np.float64(scale), "surface_name": np.str_(surface.name)}
    if surface.faces is not None:
        arrays["faces"] = surface.faces
    if surface.normals is not None:
        arrays["normals"] = surface.normals
    if target is not None:
        arrays["target"] = target
    for key, value in surface.fields.items():
        arrays[f"field:{key}"] = value
    np.savez(buffer, **arrays)
    atomic_write_bytes(path, buffer.getvalue())


def _read_shape(path: Path) -> tuple[Surface, np.ndarray | None, float]:
    """Read a shape cache entry; :class:`DatasetError` naming the file if it is truncated or corrupt.

    Every array is read in full, so the zip CRC of each member is checked: a damaged file cannot pass.
    """
    try:
        with np.load(path, allow_pickle=False) as data:
            fields = {key[6:]: data[key] for key in data.files if key.startswith("field:")}
            surface = Surface(
                data["vertices"],
                data["faces"] if "faces" in data.files else None,
                data["normals"] if "normals" in data.files else None,
                fields,
                str(data["surface_name"]),
            )
            target = data["target"] if "target" in data.files else None
            return surface, target, float(data["scale"])
    except FileNotFoundError:
        raise
    except Exception as error:  # BadZipFile, EOFError, KeyError, ValueError, zlib.error ...
        raise DatasetError(f"{path}: shape cache file is unreadable ({type(error).__name__}: {error}); "
                           "delete it or run the preprocessing again to rebuild it") from None


def _usable_cache_entry(path: Path) -> bool:
    """True if the cache entry exists and reads back; a damaged one is reported (named) and removed."""
    if not path.is_file():
        return False
    try:
        _read_shape(path)
        return True
    except DatasetError as error:
        warnings.warn(f"{error} -- rebuilding it", RuntimeWarning, stacklevel=3)
        logger.warning("%s -- rebuilding it", error)
        try:
            path.unlink()
        except OSError:
            pass  # rebuilt and atomically replaced anyway
        return False


# ------------------------------------------------------------------------------------------ per-shape work
def _normalise(surface: Surface, target, target_area: float | None, target_exponent: float, repair: bool):
    """Validate, scale to ``target_area`` (None: keep), scale the target with its area exponent."""
    surface = validate_surface(surface, repair=repair)
    if target_area is None:
        return surface, (None if target is None else np.asarray(target)), 1.0
    carry = target is not None and target_exponent != 0
    if carry:
        target = np.asarray(target, dtype=np.float64)
        if target.shape[0] != surface.n_vertices:
            raise DatasetError(f"{surface.name}: target has {target.shape[0]} values but the surface has "
                               f"{surface.n_vertices} vertices")
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
        surface, target, scale = _normalise(surface, target, target_area, source.target_exponent, repair)
        if target is not None and np.asarray(target).shape[0] != surface.n_vertices:
            raise DatasetError(f"{surface.name}: target has {np.asarray(target).shape[0]} values but the surface "
                               f"has {surface.n_vertices} vertices")
        for config in configs:
            build_patch_operator(surface, config, cache_dir=cache_dir)
        if cache_path is not None:
            _write_shape(cache_path, surface, target, scale)
        return source.name, None
    except Exception as error:  # reported by name; the other shapes go on
        message = str(error) or type(error).__name__
        if not isinstance(error, (ValueError, OSError)):
            message = f"{type(error).__name__}: {message}"
        return source.name, message


def _worker_init() -> None:
    # Several workers share few cores: one thread each avoids oversubscription.
    torch.set_num_threads(1)


def _pool_context():
    """Start method for the worker pool.

    forkserver (or spawn) starts workers from a fresh interpreter, never a fork of a process that may
    already run torch/OpenMP threads. Both re-import the main script in each worker, which is impossible
    when the main module is not a real file (``python - < script``); fork is used there.
    """
    methods = multiprocessing.get_all_start_methods()
    main_file = getattr(sys.modules.get("__main__"), "__file__", None)
    if main_file is not None and not os.path.isfile(main_file) and "fork" in methods:
        return multiprocessing.get_context("fork")
    if "forkserver" not in methods:
        return multiprocessing.get_context("spawn")
    context = multiprocessing.get_context("forkserver")
    # The fork server imports torch and zernet once; every worker forked from it starts with them loaded
    # instead of spending seconds importing them itself (which dominated the time for small shapes).
    context.set_forkserver_preload(["zernet.data.preprocess"])
    return context


def _run_pool(jobs: list, workers: int, in_flight_limit: int, record) -> set[str]:
    """Run jobs in a process pool with at most ``in_flight_limit`` submitted at once; returns the names
    finished (all of them unless the pool broke)."""
    from concurrent.futures.process import BrokenProcessPool

    finished: set[str] = set()

    def collect(futures) -> None:
        for future in futures:
            name, error = future.result()
            finished.add(name)
            record(name, error)

    try:
        with ProcessPoolExecutor(workers, mp_context=_pool_context(), initializer=_worker_init) as pool:
            running: set = set()
            for job in jobs:
                running.add(pool.submit(_prepare_one, job))
                if len(running) >= in_flight_limit:
                    done, running = wait(running, return_when=FIRST_COMPLETED)
                    collect(done)
            collect(running)
    except BrokenProcessPool as error:
        logger.warning("preprocessing pool broke: %s", error)
    return finished


#: Reason recorded for a shape whose worker process died while working on it.
WORKER_DIED = ("the worker process died while preprocessing this shape (killed, e.g. by the out-of-memory "
               "killer, or crashed in native code)")


def _prepare_isolated(job: tuple) -> tuple[str, str | None] | None:
    """Run one job in a fresh one-worker pool; (name, WORKER_DIED) if that worker dies, None if no pool starts."""
    from concurrent.futures.process import BrokenProcessPool

    try:
        with ProcessPoolExecutor(1, mp_context=_pool_context(), initializer=_worker_init) as pool:
            return pool.submit(_prepare_one, job).result()
    except BrokenProcessPool:
        return job[0].name, WORKER_DIED
    except OSError:  # no processes can be started here at all
        return None


def preprocess_shapes(
    sources: Sequence[ShapeSource],
    patch_configs,
    cache_dir: str | os.PathLike,
    target_area: float | None,
    workers: int | None = None,
    repair: bool = False,
    progress: bool = True,
    max_in_flight: int | None = None,
) -> dict[str, str]:
    """Preprocess every source into ``cache_dir`` (see the module docstring). Returns {name: failure reason}.

    workers: processes to use; None = number of CPUs (at most the number of shapes to do); 0 or 1 = in this
        process. Pool workers start from a fresh interpreter (forkserver/spawn; see ``_pool_context``), so a
        script calling this needs the usual ``if __name__ == "__main__":`` guard. If the pool breaks, the
        remaining shapes are processed in this process with a warning.
    max_in_flight: shapes submitted but not finished at any time (default 2 per worker), which bounds memory.
    """
    from tqdm.auto import tqdm

    configs = as_patch_configs(patch_configs)
    cache_dir = Path(cache_dir)
    cache_dir.mkdir(parents=True, exist_ok=True)
    names = [s.name for s in sources]
    if len(set(names)) != len(names):
        raise DatasetError(f"shape names must be unique; repeated: {sorted({n for n in names if names.count(n) > 1})[:5]}")

    jobs = []
    for source in sources:
        path = _cache_path(cache_dir, source, target_area, configs, repair)
        if path is None or not _usable_cache_entry(path):
            jobs.append((source, configs, str(cache_dir), target_area, repair, path))
    if len(jobs) < len(sources):
        logger.info("preprocess: %d of %d shapes already cached, %d to do", len(sources) - len(jobs),
                    len(sources), len(jobs))
    failures: dict[str, str] = {}
    bar = tqdm(total=len(sources), initial=len(sources) - len(jobs), desc="preprocess", unit="shape",
               disable=not progress or not jobs, leave=False)

    def record(name: str, error: str | None) -> None:
        if error is not None:
            failures[name] = error
            logger.warning("preprocessing %s failed: %s", name, error)
            bar.set_postfix(failed=len(failures))
        bar.update(1)

    if workers is None:
        workers = os.cpu_count() or 1
    workers = max(0, min(int(workers), len(jobs)))
    try:
        if workers <= 1:
            for job in jobs:
                record(*_prepare_one(job))
        else:
            done_names = _run_pool(jobs, workers, max_in_flight or 2 * workers, record)
            leftover = [job for job in jobs if job[0].name not in done_names]
            if leftover:
                # The pool broke: a worker was killed (e.g. out of memory) or crashed, or workers cannot start
                # here. Each remaining shape then runs in its own one-worker pool, so a shape that kills its
                # worker is reported by name instead of taking this process down when retried here. Only if
                # no worker ever finished a shape (a start-up problem) are the shapes processed in this process.
                warnings.warn(f"preprocessing worker pool failed; processing the remaining {len(leftover)} shapes "
                              "one at a time in fresh worker processes", RuntimeWarning, stacklevel=2)
                outcomes = [_prepare_isolated(job) for job in leftover]
                workers_work = bool(done_names) or any(o is not None and o[1] != WORKER_DIED for o in outcomes)
                for job, outcome in zip(leftover, outcomes):
                    if outcome is None or (outcome[1] == WORKER_DIED and not workers_work):
                        outcome = _prepare_one(job)
                    record(*outcome)
    finally:
        bar.close()
    return failures


def _make_record(surface: Surface, target, scale: float, name: str, configs, cache_dir, task: str,
                 feature_kind: str) -> ShapeRecord:
    operators = [build_patch_operator(surface, config, cache_dir=cache_dir) for config in configs]
    geometry = Geometry(operators=operators, edge_index=mesh_edge_index(surface))
    return ShapeRecord(
        name=name,
        surface=surface,
        features=compute_features(surface, feature_kind, operators, cache_dir=cache_dir),
        target=_as_target(target, task, surface.n_vertices, surface.name),
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
        with np.load(self.path, allow_pickle=False) as data:
            if "target" not in data.files:
                return None
            return _as_target(data["target"], self.task, int(data["vertices"].shape[0]), self.name)

    def __call__(self) -> ShapeRecord:
        surface, target, scale = _read_shape(self.path)
        return _make_record(surface, target, scale, self.name, self.configs, self.cache_dir, self.task,
                            self.feature_kind)


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
    surface, target, scale = _normalise(surface, target, target_area, target_exponent, repair)
    name = name or Path(surface.name).stem
    return _make_record(surface, target, scale, name, configs, None if cache_dir is None else str(cache_dir),
                        task, feature_kind)


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
    strict: bool = False,
    repair: bool = False,
    progress: bool = True,
    in_memory: bool | None = None,
    info: dict[str, Any] | None = None,
    correspondence: bool = False,
) -> ShapeDataset:
    """Preprocess ``sources`` and assemble the :class:`ShapeDataset`.

    Args:
        sources: one :class:`ShapeSource` per shape; their order is the data set's order.
        patch_configs: PatchConfig (or dicts), one per scale.
        cache_dir: folder for the shape cache and the patch operators' cache.
        target_area: area every surface is scaled to (None: keep the file's scale).
        task, num_classes: see :class:`ShapeDataset`.
        split_names: {"train": names, "test": names, ...}; a "val" split is carved from "train"
            (``n_val`` shapes or a fraction, seeded by ``seed``) unless split_names already has one.
            Shapes that failed are dropped from every split.
        feature_kind: parts of :data:`~zernet.data.base.FEATURE_PARTS` joined by '+'.
        workers, repair, progress: see :func:`preprocess_shapes`.
        strict: raise :class:`PreprocessError` if any shape fails (otherwise only if all fail).
        in_memory: hold every record in memory; None decides by size (:data:`IN_MEMORY_VERTEX_LIMIT`).
        info: extra description stored on the data set.
        correspondence: mark the data set as template correspondence (class = vertex index).
    """
    feature_parts(feature_kind)  # an unknown kind fails here, before any preprocessing
    if not sources:
        raise DatasetError("no shapes to preprocess")
    configs = as_patch_configs(patch_configs)
    cache_dir = Path(cache_dir)
    failures = preprocess_shapes(sources, configs, cache_dir, target_area, workers=workers, repair=repair,
                                 progress=progress)
    if failures:
        listing = "\n".join(f"  {name}: {reason}" for name, reason in failures.items())
        message = f"{len(failures)} of {len(sources)} shapes failed to preprocess:\n{listing}"
        if strict or len(failures) == len(sources):
            raise PreprocessError(message, failures)
        warnings.warn(message + "\n(continuing without them)", RuntimeWarning, stacklevel=2)

    kept = [s for s in sources if s.name not in failures]
    loaders = []
    for source in kept:
        path = _cache_path(cache_dir, source, target_area, configs, repair)
        if path is None:
            # No content key: nothing on disk to reload from, so this shape is built here and kept in memory.
            surface, target = source.load()
            surface, target, scale = _normalise(surface, target, target_area, source.target_exponent, repair)
            loaders.append(_make_record(surface, target, scale, source.name, configs, str(cache_dir), task,
                                        feature_kind))
        else:
            loaders.append(_CachedRecord(path, source.name, configs, str(cache_dir), task, feature_kind))

    names = [s.name for s in kept]
    position = {name: i for i, name in enumerate(names)}
    unknown = sorted({n for split in split_names.values() for n in split} - {s.name for s in sources})
    if unknown:
        raise DatasetError(f"splits name shapes that are not in the data set: {unknown[:5]}")
    splits = {key: sorted(position[n] for n in value if n in position) for key, value in split_names.items()}
    if "val" not in splits:
        splits["train"], splits["val"] = carve_validation(splits.get("train", []), n_val, seed)
    splits.setdefault("test", [])

    if in_memory is None:
        in_memory = _estimate_vertices(loaders) * len(configs) <= IN_MEMORY_VERTEX_LIMIT
    if in_memory:
        loaders = [item if isinstance(item, ShapeRecord) else item() for item in loaders]
    in_channels = feature_channels(feature_kind, [c.n_max for c in configs] or 5)
    return ShapeDataset(loaders, names, task, num_classes, splits, configs, in_channels,
                        feature_kind, target_area, failures, info, correspondence)


def _estimate_vertices(loaders) -> int:
    """Total vertex count of the data set (reads only the vertex arrays of the cache files)."""
    total = 0
    for item in loaders:
        if isinstance(item, ShapeRecord):
            total += item.n_vertices
        else:
            with np.load(item.path, allow_pickle=False) as data:
                total += int(data["vertices"].shape[0])
    return total
