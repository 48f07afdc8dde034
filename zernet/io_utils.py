"""Atomic file writes: a reader never sees a half-written cache or checkpoint."""

from __future__ import annotations

import io
import os
import shutil
import tempfile
from pathlib import Path

import torch


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
