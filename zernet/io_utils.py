"""Atomic file writes (a reader never sees a half-written cache, checkpoint or metrics file) and plain values."""

from __future__ import annotations

import io
import json
import math
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

__all__ = ["atomic_write_bytes", "snapshot_file", "atomic_save_torch", "write_json", "json_ready", "plain"]


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` via a temporary file in the same folder, fsync, then rename.

    If anything fails (a full disk, a kill), the previous file at ``path`` is left untouched and no temporary
    file is left behind; an ``OSError`` (e.g. ENOSPC) is re-raised with ``path`` as its file name, so the
    message says which write failed.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        # mkstemp makes the file private (0600); give it the mode a plain open() would (0644 under umask 022).
        os.fchmod(fd, 0o666 & ~_umask())
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException as error:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        if isinstance(error, OSError) and error.errno is not None and error.filename is None:
            # OSError(errno, ...) maps to the same subclass (PermissionError, ...); now it names the file.
            raise OSError(error.errno, f"{error.strerror or error} (while writing)", str(path)) from error
        raise
    return path


def _umask() -> int:
    """The process's file-creation mask (read by setting it and restoring it at once)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def snapshot_file(source: str | os.PathLike, destination: str | os.PathLike) -> Path | None:
    """Make ``destination`` an exact, complete copy of ``source`` (atomically); None if ``source`` is missing.

    Used to keep the previous checkpoint before the next one replaces it: a hard link costs no copy (the
    atomic rename in :func:`atomic_write_bytes` then gives ``source`` a new file while ``destination`` keeps
    the old one); file systems without hard links get a byte copy.
    """
    source, destination = Path(source), Path(destination)
    if not source.is_file():
        return None
    tmp = destination.with_name(f".{destination.name}.{os.getpid()}.snapshot.tmp")
    try:
        if tmp.exists():
            tmp.unlink()
        try:
            os.link(source, tmp)
        except OSError:
            shutil.copyfile(source, tmp)
        os.replace(tmp, destination)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    return destination


def atomic_save_torch(obj, path: str | os.PathLike) -> Path:
    """``torch.save`` made atomic (see :func:`atomic_write_bytes`)."""
    # Imported here: zernet.geometry writes through this module and imports no torch (its layer is below it).
    import torch

    buffer = io.BytesIO()
    torch.save(obj, buffer)
    return atomic_write_bytes(path, buffer.getvalue())


def write_json(path: str | os.PathLike, data: dict) -> Path:
    """Write ``data`` as indented, valid (strict) JSON, atomically: numpy scalars and arrays become numbers
    and lists, and an undefined number (NaN, infinity) becomes ``null``."""
    text = json.dumps(json_ready(data), indent=2, allow_nan=False)
    return atomic_write_bytes(path, (text + "\n").encode("utf-8"))


def json_ready(value):
    """``value`` with JSON types only: numpy scalars and arrays as numbers and lists, tuples as lists,
    paths as strings, and NaN or infinite numbers as None (``null``: undefined)."""
    if isinstance(value, dict):
        return {str(k): json_ready(v) for k, v in value.items()}
    if isinstance(value, np.ndarray):
        return json_ready(value.tolist())
    if isinstance(value, (list, tuple)):
        return [json_ready(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if value is None or isinstance(value, (int, str)):
        return value
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def plain(value):
    """``value`` with plain YAML/JSON types only: tuples become lists, paths strings, numpy scalars numbers."""
    if isinstance(value, dict):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (np.floating,)):
        return float(value)
    return value
