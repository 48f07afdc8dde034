"""The on-disk cache of patch operators: cache keys and the array file format training reads without decoding.

:func:`zernet.operators.build_patch_operator` with ``cache_dir`` stores one ``<key>.zop`` per (geometry,
config), keyed by :func:`cache_key` = ``sha256(geometry_hash, config JSON, polar backend used and its version, format
version)``: a file written by another backend version, another fit or an older format gets another key
(and a stale file under the same name is rejected by its stored version), so it is rebuilt, never misread.
A file of an older format (format 4's ``<old key>.zop``, format 3's ``<old key>.npz``) is named in a
:class:`CacheWarning` when its operator is rebuilt (it is no longer read and can be deleted).

**Array files** (:func:`write_arrays`, :func:`read_arrays`): an 8-byte magic, the length of a JSON header,
the header (format version, key, free ``meta`` values, the sha256 of the data and every array's dtype,
shape and offset), then the raw arrays, each at a 64-byte aligned offset. Reading maps the file into memory
(``mmap``) and returns numpy views of it: nothing is parsed or decompressed, a page is read when it is first
touched, and a process holding many operators holds page cache, not copies. The sha256 of the data is
checked on the first read of a file in a process only (a file rewritten since has another size or
modification time and is checked again): a streamed data set maps every file once per epoch.
:func:`read_arrays` raises ``ValueError`` naming the file when it is unreadable, truncated, corrupt, of
another format version or for another key; the builder then warns with :class:`CacheWarning` and rebuilds.
Files are written atomically (:func:`zernet.io_utils.atomic_write_bytes`: a reader sees the old file or the
new one, and a mapped old file stays valid after a rename replaces it).

A patch operator's file holds what is costly to compute and small to keep: the patches' sample geometry
(for each vertex its samples with their geodesic polar coordinates, the samples' interpolation from the
vertices, the tangent frames; float32, indices in their narrowest types;
:meth:`zernet.operators.PatchOperator.to_arrays`). Reading it fits each patch again and carries the fit to
the vertices (:func:`zernet.operators.patch.fit_pairs`): with the shipped FAUST settings a 6,890-vertex
body's file is 5.1 MB and its float16 pairs in memory 19.4 MB, read in about 0.4 s at two threads (format 5,
the pairs in the file: 23.7 MB; format 4, the float32 CSR matrix and its transpose: 183 MB;
``benchmarks/speed/bench_operator.py``). Beside it, ``<key>.transport.zop`` keeps the operator's vertex pairs and transport angles once a
directional model has asked for them (:func:`zernet.operators.directional.patch_transport`).

This module knows arrays, not operators: :class:`~zernet.operators.PatchOperator` turns itself into
arrays and back (``to_arrays`` / ``from_arrays``, ``save`` / ``load``). The checked ``.npz`` payload of
:func:`write_payload` / :func:`read_payload` remains for small files of other modules.
"""

from __future__ import annotations

import hashlib
import io
import json
import mmap
import os
import struct
from pathlib import Path

import numpy as np
import scipy.sparse

from zernet.geometry import BACKEND_VERSIONS, resolve_backend
from zernet.io_utils import atomic_write_bytes

# Versions (:func:`_file_version`) of the files whose checksum this process has verified or written.
_CHECKED: set[tuple[str, int, int, int]] = set()

__all__ = [
    "FORMAT_VERSION",
    "CacheWarning",
    "cache_key",
    "cache_path",
    "legacy_cache_paths",
    "pack_arrays",
    "unpack_arrays",
    "write_arrays",
    "read_arrays",
    "pack_payload",
    "unpack_payload",
    "sparse_to_arrays",
    "sparse_from_arrays",
    "write_payload",
    "read_payload",
]

#: Version 2: degree-weighted ridge, all samples within r0 by default, backend and its version in the key.
#: Version 3: the ridge weighs every basis but the piston equally (operators of version 2 differ).
#: Version 4: raw memory-mapped arrays (:func:`write_arrays`): float32 matrix with its stored transpose.
#: Version 5: the matrix as vertex pairs (:class:`zernet.operators.pairs.VertexPairs`), values in the
#: config's ``precision``, no stored transpose, the patch samples as flat lists.
#: Version 6: the patches' sample geometry only (flat patch lists, interpolation, frames, in float32): the
#: matrix is fitted again on reading.
FORMAT_VERSION = 6

#: Version of the checked ``.npz`` payload (:func:`pack_payload`), which other modules use for small files.
PAYLOAD_VERSION = 3

#: The first bytes of an array file (:func:`pack_arrays`).
MAGIC = b"ZNARRAY1"
_ALIGN = 64


class CacheWarning(UserWarning):
    """A cached operator file could not be trusted (corrupt, truncated, stale) and is being rebuilt."""


def cache_key(surface, config, backend: str | None = None) -> str:
    """sha256 of the surface's ``geometry_hash()``, the config (``to_dict()``, JSON with sorted keys), the
    polar backend used on this surface (``backend``, default :func:`zernet.geometry.resolve_backend` of
    ``config.backend``) with its version (:data:`zernet.geometry.BACKEND_VERSIONS`) and :data:`FORMAT_VERSION`."""
    backend = resolve_backend(surface, config.backend) if backend is None else backend
    return _key(surface, config.to_dict(), backend, FORMAT_VERSION)


def _key(surface, config: dict, backend: str, version: int) -> str:
    text = json.dumps(
        {
            "geometry": surface.geometry_hash(),
            "config": config,
            "backend": backend,
            "backend_version": BACKEND_VERSIONS.get(backend),
            "version": version,
        },
        sort_keys=True,
    )
    return hashlib.sha256(text.encode()).hexdigest()


def cache_path(cache_dir: str | os.PathLike, key: str) -> Path:
    """The file of ``key`` in ``cache_dir``."""
    return Path(cache_dir) / f"{key}.zop"


def legacy_cache_paths(cache_dir: str | os.PathLike, surface, config, backend: str) -> list[Path]:
    """Where formats 5 (``.zop``, the vertex pairs), 4 (``.zop``, the CSR matrix and its transpose) and 3 (a
    checked ``.npz``) kept the same operator; the keys of 4 and 3 knew no ``precision``."""
    old_config = {name: value for name, value in config.to_dict().items() if name != "precision"}
    return [
        Path(cache_dir) / f"{_key(surface, config.to_dict(), backend, 5)}.zop",
        Path(cache_dir) / f"{_key(surface, old_config, backend, 4)}.zop",
        Path(cache_dir) / f"{_key(surface, old_config, backend, 3)}.npz",
    ]


# ---------------------------------------------------------------------------------------------- array files
def _aligned(offset: int) -> int:
    return -(-offset // _ALIGN) * _ALIGN


def pack_arrays(arrays: dict[str, np.ndarray], key: str = "", meta: dict | None = None) -> bytearray:
    """The bytes of an array file (module docstring): ``arrays`` (any numeric dtypes, C order) with ``key``,
    the format version and ``meta`` (JSON values) in the header. Built in one buffer of the file's size."""
    entries, offset = [], 0
    arrays = {name: np.ascontiguousarray(array) for name, array in arrays.items()}
    digest = hashlib.sha256()
    for name, array in arrays.items():
        if array.dtype.hasobject or array.dtype.kind in "USV":
            raise TypeError(f"array {name!r} has dtype {array.dtype}: only numeric arrays go in an array file")
        digest.update(bytes(_aligned(offset) - offset))
        offset = _aligned(offset)
        entries.append({"name": name, "dtype": array.dtype.str, "shape": list(array.shape), "offset": offset})
        digest.update(memoryview(array).cast("B"))
        offset += array.nbytes
    header = json.dumps(
        {
            "version": FORMAT_VERSION,
            "key": key,
            "meta": meta or {},
            "size": offset,
            "sha256": digest.hexdigest(),
            "arrays": entries,
        }
    ).encode()
    start = _aligned(len(MAGIC) + 8 + len(header))
    out = bytearray(start + offset)
    out[: len(MAGIC) + 8 + len(header)] = MAGIC + struct.pack("<Q", len(header)) + header
    for entry, array in zip(entries, arrays.values()):
        out[start + entry["offset"] : start + entry["offset"] + array.nbytes] = memoryview(array).cast("B")
    return out


def unpack_arrays(
    buffer, key: str | None = None, name: str = "<bytes>", check_sum: bool = True
) -> tuple[dict[str, np.ndarray], dict]:
    """Inverse of :func:`pack_arrays`: ``(arrays, meta)``, the arrays read-only views of ``buffer`` (bytes,
    or an ``mmap``). ``ValueError`` naming ``name`` on any inconsistency (not an array file, truncated, other
    format version, other key when ``key`` is given, checksum mismatch unless ``check_sum`` is off)."""
    view = memoryview(buffer)
    try:
        if bytes(view[: len(MAGIC)]) != MAGIC:
            raise ValueError("no array-file signature")
        (length,) = struct.unpack("<Q", view[len(MAGIC) : len(MAGIC) + 8])
        if len(MAGIC) + 8 + length > len(view):
            raise ValueError("header runs past the end of the file")
        header = json.loads(bytes(view[len(MAGIC) + 8 : len(MAGIC) + 8 + length]))
        version, stored_key, size = int(header["version"]), str(header["key"]), int(header["size"])
        entries, checksum = header["arrays"], str(header["sha256"])
    except Exception as error:  # noqa: BLE001 - any failure here means "not a valid file"
        raise ValueError(f"{name}: not a readable operator file ({type(error).__name__}: {error})") from error
    if version != FORMAT_VERSION:
        raise ValueError(f"{name}: format version {version}, expected {FORMAT_VERSION}")
    if key is not None and stored_key != key:
        raise ValueError(f"{name}: stored key {stored_key[:12]}... does not match {key[:12]}...")
    start = _aligned(len(MAGIC) + 8 + length)
    if len(view) != start + size:
        raise ValueError(f"{name}: {len(view)} bytes, expected {start + size} (truncated or overlong)")
    data = view[start:]
    if check_sum and hashlib.sha256(data).hexdigest() != checksum:
        raise ValueError(f"{name}: payload checksum mismatch (file corrupt)")
    try:
        arrays = {}
        for entry in entries:
            dtype, shape = np.dtype(entry["dtype"]), tuple(int(n) for n in entry["shape"])
            count = int(np.prod(shape, dtype=np.int64))
            array = np.frombuffer(data, dtype=dtype, count=count, offset=int(entry["offset"]))
            arrays[str(entry["name"])] = array.reshape(shape)
    except Exception as error:  # noqa: BLE001
        raise ValueError(f"{name}: inconsistent operator payload ({type(error).__name__}: {error})") from error
    return arrays, dict(header.get("meta") or {})


def write_arrays(
    path: str | os.PathLike, arrays: dict[str, np.ndarray], key: str = "", meta: dict | None = None
) -> Path:
    """Write :func:`pack_arrays` atomically to ``path``; the file counts as checked in this process."""
    path = atomic_write_bytes(path, pack_arrays(arrays, key, meta))
    _CHECKED.add(_file_version(path))
    return path


def read_arrays(path: str | os.PathLike, key: str | None = None) -> tuple[dict[str, np.ndarray], dict]:
    """Map a file written by :func:`write_arrays` into memory: ``(arrays, meta)``, read-only views of the
    mapping; ``ValueError`` naming the file if it cannot be trusted. The checksum is verified on the first
    read of this version of the file in this process (module docstring)."""
    path = Path(path)
    version = _file_version(path)  # before the read: a file replaced meanwhile is then checked on its next read
    with open(path, "rb") as handle:
        if version[1] == 0:
            raise ValueError(f"{path}: empty file")
        mapped = mmap.mmap(handle.fileno(), 0, access=mmap.ACCESS_READ)  # stays valid after the file closes
    arrays, meta = unpack_arrays(mapped, key=key, name=str(path), check_sum=version not in _CHECKED)
    _CHECKED.add(version)
    return arrays, meta


def _file_version(path: Path) -> tuple[str, int, int, int]:
    """What tells one version of a file from another: its path, size, modification time and inode (an
    atomic replacement is a new inode)."""
    status = path.stat()
    return str(path.resolve()), status.st_size, status.st_mtime_ns, status.st_ino


def pack_payload(arrays: dict[str, np.ndarray], key: str = "") -> bytes:
    """``.npz`` bytes: the arrays as an inner npz payload plus its sha256, ``key`` and :data:`PAYLOAD_VERSION`."""
    inner = io.BytesIO()
    np.savez(inner, **arrays)
    payload = inner.getvalue()
    outer = io.BytesIO()
    np.savez(
        outer,
        payload=np.frombuffer(payload, dtype=np.uint8),
        checksum=np.asarray(hashlib.sha256(payload).hexdigest()),
        key=np.asarray(key),
        version=np.asarray(PAYLOAD_VERSION),
    )
    return outer.getvalue()


def unpack_payload(
    data: bytes, key: str | None = None, name: str = "<bytes>", check_sum: bool = True
) -> dict[str, np.ndarray]:
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
    if version != PAYLOAD_VERSION:
        raise ValueError(f"{name}: format version {version}, expected {PAYLOAD_VERSION}")
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


def sparse_from_arrays(
    arrays: dict[str, np.ndarray], name: str, sorted_indices: bool = False
) -> scipy.sparse.csr_matrix:
    """Inverse of :func:`sparse_to_arrays`, over the same arrays (no copy). ``sorted_indices``: the writer
    sorted them (a checked file), so scipy need not scan the indices to find out."""
    matrix = scipy.sparse.csr_matrix(
        (arrays[f"{name}_data"], arrays[f"{name}_indices"], arrays[f"{name}_indptr"]),
        shape=tuple(int(s) for s in arrays[f"{name}_shape"]),
        copy=False,
    )
    if sorted_indices:
        matrix.has_sorted_indices = True
    return matrix


def write_payload(path: str | os.PathLike, arrays: dict[str, np.ndarray], key: str = "") -> Path:
    """Write :func:`pack_payload` of the arrays atomically to ``path``."""
    return atomic_write_bytes(path, pack_payload(arrays, key))


def read_payload(path: str | os.PathLike, key: str | None = None) -> dict[str, np.ndarray]:
    """Read a file written by :func:`write_payload`; ``ValueError`` naming the file if it cannot be trusted.
    The sha256 is verified on the first read of this version of the file in this process (the zip CRC of
    every array on every read)."""
    path = Path(path)
    version = _file_version(path)  # before the read: a file replaced meanwhile is then checked on its next read
    data = path.read_bytes()
    arrays = unpack_payload(data, key=key, name=str(path), check_sum=version not in _CHECKED)
    _CHECKED.add(version)
    return arrays
