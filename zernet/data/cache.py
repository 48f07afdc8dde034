"""The shape cache: one ``.npz`` file per preprocessed shape under ``cache_dir/shapes/``.

An entry holds the validated, area-normalised surface (vertices, faces, normals, fields, name), its target
and the normalisation's scale. Its file name is the shape's name plus a digest of everything that decides
its content: the source's content key, the target area and exponent, the repair flag and every patch
configuration (:func:`shape_cache_path`). An entry that exists is the marker that the shape is done; the
patch operators keep their own cache (:mod:`zernet.operators.cache`).
"""

from __future__ import annotations

import hashlib
import io
import json
import re
import warnings
from collections.abc import Sequence
from dataclasses import asdict, is_dataclass
from pathlib import Path

import numpy as np

from zernet.data.dataset import DatasetError
from zernet.data.source import ShapeSource
from zernet.geometry import Surface
from zernet.io_utils import atomic_write_bytes
from zernet.operators import PatchConfig

__all__ = [
    "CACHE_FORMAT",
    "config_fingerprint",
    "shape_cache_path",
    "write_shape",
    "read_shape",
    "usable_cache_entry",
    "read_cached_target",
    "cached_vertex_count",
]


#: Bump when the content of the shape cache files changes, so old entries are not misread.
CACHE_FORMAT = "zernet-shape-1"


def config_fingerprint(config: PatchConfig) -> dict:
    """The fields of a patch configuration, as they enter the cache digest."""
    return asdict(config) if is_dataclass(config) else dict(vars(config))


def shape_cache_path(
    cache_dir: Path, source: ShapeSource, target_area: float | None, configs: Sequence[PatchConfig], repair: bool
) -> Path | None:
    """Cache file of one shape, or None when the source has no content key."""
    if source.key is None:
        return None
    description = json.dumps(
        {
            "format": CACHE_FORMAT,
            "key": source.key,
            "area": target_area,
            "exponent": source.target_exponent,
            "repair": repair,
            "configs": [config_fingerprint(c) for c in configs],
        },
        sort_keys=True,
        default=str,
    )
    digest = hashlib.sha256(description.encode()).hexdigest()[:20]
    safe = re.sub(r"[^A-Za-z0-9_.-]+", "_", source.name)[:60]
    return Path(cache_dir) / "shapes" / f"{safe}-{digest}.npz"


def write_shape(path: Path, surface: Surface, target: np.ndarray | None, scale: float) -> None:
    """Write one entry atomically (a reader never sees half a file)."""
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


def read_shape(path: Path) -> tuple[Surface, np.ndarray | None, float]:
    """Read an entry as (surface, target, scale); :class:`DatasetError` naming the file if it is damaged.

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
        raise DatasetError(
            f"{path}: shape cache file is unreadable ({type(error).__name__}: {error}); "
            "delete it or run the preprocessing again to rebuild it"
        ) from None


def read_cached_target(path: Path) -> tuple[np.ndarray | None, int]:
    """Only the target of an entry and the shape's vertex count (no surface built)."""
    with np.load(path, allow_pickle=False) as data:
        target = data["target"] if "target" in data.files else None
        return target, int(data["vertices"].shape[0])


def cached_vertex_count(path: Path) -> int:
    """Vertex count of an entry (reads only its vertex array)."""
    with np.load(path, allow_pickle=False) as data:
        return int(data["vertices"].shape[0])


def usable_cache_entry(path: Path) -> bool:
    """True if the entry exists and reads back; a damaged one is reported (named) and removed."""
    if not path.is_file():
        return False
    try:
        read_shape(path)
        return True
    except DatasetError as error:
        # One report (a warning; the command line prints it as one line), not a warning and a log line too.
        reason = str(error).split("; delete it")[0]  # the advice is taken here: it is rebuilt
        warnings.warn(f"{reason}; rebuilding it", RuntimeWarning, stacklevel=3)
        try:
            path.unlink()
        except OSError:
            pass  # rebuilt and atomically replaced anyway
        return False
