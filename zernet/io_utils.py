"""Atomic file writes (a reader never sees a half-written cache, checkpoint or metrics file) and plain values."""

from __future__ import annotations

import io
import json
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
import torch

__all__ = ["atomic_write_bytes", "snapshot_file", "atomic_save_torch", "write_json", "plain"]


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
    buffer = io.BytesIO()
    torch.save(obj, buffer)
    return atomic_write_bytes(path, buffer.getvalue())


def write_json(path: str | os.PathLike, data: dict) -> Path:
    """Write ``data`` as indented JSON, atomically; numpy scalars and arrays become numbers and lists."""
    def default(value):
        if isinstance(value, (np.integer,)):
            return int(value)
        if isinstance(value, (np.floating,)):
            return float(value)
        if isinstance(value, np.ndarray):
            return value.tolist()
        raise TypeError(f"not JSON serialisable: {type(value).__name__}")

    text = json.dumps(data, indent=2, default=default, allow_nan=True)
    return atomic_write_bytes(path, (text + "\n").encode("utf-8"))


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
