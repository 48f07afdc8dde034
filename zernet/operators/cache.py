"""The on-disk cache of patch operators: cache keys and the checked ``.npz`` file format.

:func:`zernet.operators.build_patch_operator` with ``cache_dir`` stores one ``<key>.npz`` per (geometry,
config), keyed by :func:`cache_key` = ``sha256(geometry_hash, config JSON, polar backend used and its version, format
version)``: a file written by another backend version, another fit or an older format gets another key
(and a stale file under the same name is rejected by its stored version), so it is rebuilt, never misread. The file holds
the assembled matrix and the patch geometry (sample ids, polar coordinates, frames, interpolation): about
150 MB for 6,890 vertices with every sample within r0. Beside it, ``<key>.transport.npz`` (same checked format)
keeps the operator's vertex pairs and transport angles once a directional model has asked for them
(:func:`zernet.operators.directional.patch_transport`).

A file is an outer ``.npz`` holding an inner ``.npz`` payload, its sha256, the key and
:data:`FORMAT_VERSION`; :func:`unpack_payload` rejects (``ValueError`` naming the file) a file that is
unreadable, truncated, corrupt, stale or for another key, and the builder then warns with
:class:`CacheWarning` and rebuilds. :func:`read_payload` checks the sha256 on the first read of a file in a
process only (a file rewritten since has another size or modification time and is checked again): a streamed
data set reads every file once per epoch, and hashing 150 MB each time cost a third of a second per step;
the zip CRC of every array is still checked on every read. Files are written atomically (:func:`zernet.io_utils.atomic_write_bytes`).
This module knows arrays, not operators: :class:`~zernet.operators.PatchOperator` turns itself into
arrays and back (``to_bytes`` / ``from_bytes``, ``save`` / ``load``).
"""

from __future__ import annotations

import hashlib
import io
import json
import os
from pathlib import Path

import numpy as np
import scipy.sparse

from zernet.geometry import BACKEND_VERSIONS, resolve_backend
from zernet.io_utils import atomic_write_bytes

__all__ = [
    "FORMAT_VERSION",
    "CacheWarning",
    "cache_key",
    "cache_path",
    "pack_payload",
    "unpack_payload",
    "sparse_to_arrays",
    "sparse_from_arrays",
    "write_payload",
    "read_payload",
]

#: Version 2: degree-weighted ridge, all samples within r0 by default, backend and its version in the key.
#: Version 3: the ridge weighs every basis but the piston equally (operators of version 2 differ).
FORMAT_VERSION = 3


class CacheWarning(UserWarning):
    """A cached operator file could not be trusted (corrupt, truncated, stale) and is being rebuilt."""


def cache_key(surface, config, backend: str | None = None) -> str:
    """sha256 of the surface's ``geometry_hash()``, the config (``to_dict()``, JSON with sorted keys), the
    polar backend used on this surface (``backend``, default :func:`zernet.geometry.resolve_backend` of
    ``config.backend``) with its version (:data:`zernet.geometry.BACKEND_VERSIONS`) and the format version."""
    backend = resolve_backend(surface, config.backend) if backend is None else backend
    text = json.dumps({"geometry": surface.geometry_hash(), "config": config.to_dict(), "backend": backend,
                       "backend_version": BACKEND_VERSIONS.get(backend), "version": FORMAT_VERSION}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()


def cache_path(cache_dir: str | os.PathLike, key: str) -> Path:
    """The file of ``key`` in ``cache_dir``."""
    return Path(cache_dir) / f"{key}.npz"


def pack_payload(arrays: dict[str, np.ndarray], key: str = "") -> bytes:
    """``.npz`` bytes: the arrays as an inner npz payload plus its sha256, ``key`` and the format version."""
    inner = io.BytesIO()
    np.savez(inner, **arrays)
    payload = inner.getvalue()
    outer = io.BytesIO()
    np.savez(
        outer,
        payload=np.frombuffer(payload, dtype=np.uint8),
        checksum=np.asarray(hashlib.sha256(payload).hexdigest()),
        key=np.asarray(key),
        version=np.asarray(FORMAT_VERSION),
    )
    return outer.getvalue()


def unpack_payload(data: bytes, key: str | None = None, name: str = "<bytes>",
                   check_sum: bool = True) -> dict[str, np.ndarray]:
    """Inverse of :func:`pack_payload`; ``ValueError`` naming ``name`` on any inconsistency (unreadable,
    other format version, other key when ``key`` is given, checksum mismatch unless ``check_sum`` is off)."""
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as outer:
            version = int(outer["version"])
            stored_key = str(outer["key"])
            checksum = str(outer["checksum"])
            payload = outer["payload"].tobytes()
    except Exception as error:  # noqa: BLE001 - any read failure means "not a valid file"
        raise ValueError(f"{name}: not a readable operator file ({type(error).__name__}: {error})") from error
    if version != FORMAT_VERSION:
        raise ValueError(f"{name}: format version {version}, expected {FORMAT_VERSION}")
    if key is not None and stored_key != key:
        raise ValueError(f"{name}: stored key {stored_key[:12]}... does not match {key[:12]}...")
    if check_sum and hashlib.sha256(payload).hexdigest() != checksum:
        raise ValueError(f"{name}: payload checksum mismatch (file corrupt)")
    try:
        with np.load(io.BytesIO(payload), allow_pickle=False) as arrays:
            return {entry: arrays[entry] for entry in arrays.files}
    except Exception as error:  # noqa: BLE001
        raise ValueError(f"{name}: inconsistent operator payload ({type(error).__name__}: {error})") from error


def sparse_to_arrays(name: str, matrix: scipy.sparse.csr_matrix) -> dict[str, np.ndarray]:
    """A CSR matrix as the arrays ``<name>_data``, ``_indices``, ``_indptr`` and ``_shape``."""
    return {
        f"{name}_data": matrix.data,
        f"{name}_indices": matrix.indices,
        f"{name}_indptr": matrix.indptr,
        f"{name}_shape": np.asarray(matrix.shape, dtype=np.int64),
    }


def sparse_from_arrays(arrays: dict[str, np.ndarray], name: str) -> scipy.sparse.csr_matrix:
    """Inverse of :func:`sparse_to_arrays`."""
    return scipy.sparse.csr_matrix(
        (arrays[f"{name}_data"], arrays[f"{name}_indices"], arrays[f"{name}_indptr"]),
        shape=tuple(int(s) for s in arrays[f"{name}_shape"]),
    )


def write_payload(path: str | os.PathLike, arrays: dict[str, np.ndarray], key: str = "") -> Path:
    """Write :func:`pack_payload` of the arrays atomically to ``path``."""
    return atomic_write_bytes(path, pack_payload(arrays, key))


# (path, size, modification time) of the files whose checksum this process has verified.
_CHECKED: set[tuple[str, int, int]] = set()


def read_payload(path: str | os.PathLike, key: str | None = None) -> dict[str, np.ndarray]:
    """Read a file written by :func:`write_payload`; ``ValueError`` naming the file if it cannot be trusted.
    The checksum is verified on the first read of this version of the file in this process (module docstring)."""
    path = Path(path)
    status = path.stat()  # before the read: a file replaced meanwhile is then checked on its next read
    version = (str(path.resolve()), status.st_size, status.st_mtime_ns)
    data = path.read_bytes()
    arrays = unpack_payload(data, key=key, name=str(path), check_sum=version not in _CHECKED)
    _CHECKED.add(version)
    return arrays
