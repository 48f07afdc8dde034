"""Reading surfaces from files: meshes (PLY, OBJ, OFF, STL), the authors' MATLAB layout (.mat) and point
cloud arrays (.npy, .xyz, .txt). Every reader keeps the file's vertex order.

Public API: :func:`load_surface`.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence

import numpy as np
import scipy.io

from zernet.geometry.surface import Surface, SurfaceError
from zernet.geometry.validate import merge_coincident, validate_surface

__all__ = ["load_surface", "read_surface"]

_MESH_EXTENSIONS = (".ply", ".obj", ".off", ".stl")
_CLOUD_EXTENSIONS = (".npy", ".xyz", ".txt")
# Text formats whose faces are checked line by line when trimesh cannot read them.
_TEXT_MESH_EXTENSIONS = (".obj", ".off")
# PLY vertex properties that are geometry or colour, not per-vertex fields.
_PLY_NON_FIELDS = {"x", "y", "z", "nx", "ny", "nz", "red", "green", "blue", "alpha"}


def load_surface(path: str | os.PathLike, repair: bool = False, fields: Sequence[str] | None = None) -> Surface:
    """Read a mesh or a point cloud and validate it (see :func:`zernet.geometry.validate_surface`).

    Formats (by extension, case-insensitive):

    - ``.ply .obj .off .stl`` — read with trimesh, ``process=False`` (and ``maintain_order=True`` for OBJ),
      so vertices keep their order in the file: for correspondence the vertex index is the label. A PLY
      without faces is a point cloud, with its ``nx ny nz`` normals if present. Extra PLY vertex
      properties (other than position, normal and colour) become fields. STL stores every triangle with
      its own three corners, so its vertices are merged by exact position, numbered in order of first
      appearance (the original numbering of an STL file's source cannot be recovered).
    - ``.mat`` — the layout of the ZerNet authors' release (MATLAB v5, via scipy.io.loadmat): ``X`` (V, 3)
      positions, ``F`` (T, 3) **1-based** triangle indices (any integer type, e.g. uint16; without ``F``
      the file is a point cloud), and every other array with V rows, e.g. ``J2m`` (V, 1), becomes a field
      (a (V, 1) column becomes shape (V,)).
    - ``.npy`` (numpy array) and ``.xyz`` / ``.txt`` (whitespace-separated text, ``#`` comments) — point
      clouds of shape (N, 3), or (N, 6) with normals in the last three columns.

    Args:
        path: the file.
        repair: passed to :func:`zernet.geometry.validate_surface` (merge duplicate vertices, drop
            degenerate faces).
        fields: names of per-vertex fields to keep (for .mat and PLY); ``None`` keeps all. A requested
            name the file does not have is an error.

    Returns:
        the validated :class:`Surface`, ``name`` set to the path.

    Raises:
        SurfaceError: missing file, unknown extension, unreadable file, or any validation error; the
            message names the file.
    """
    return validate_surface(read_surface(path, fields), repair=repair)


def read_surface(path: str | os.PathLike, fields: Sequence[str] | None = None) -> Surface:
    """Read a surface file as it is, without validation (:func:`load_surface` validates): for
    :func:`zernet.geometry.repair_surface`, which maps a repaired surface back to the file's vertices.

    Raises:
        SurfaceError: missing file, unknown extension, unreadable file, unknown field name.
    """
    name = os.fspath(path)
    if not os.path.isfile(name):
        raise SurfaceError(f"{name}: no such file")
    extension = os.path.splitext(name)[1].lower()
    if extension in _MESH_EXTENSIONS:
        surface = _load_trimesh(name, extension)
    elif extension == ".mat":
        surface = _load_mat(name)
    elif extension in _CLOUD_EXTENSIONS:
        surface = _load_cloud_array(name, extension)
    else:
        known = ", ".join(_MESH_EXTENSIONS + (".mat",) + _CLOUD_EXTENSIONS)
        raise SurfaceError(f"{name}: unknown surface file extension {extension!r} (known: {known})")
    if fields is not None:
        surface = _select_fields(surface, [str(key) for key in fields])
    return surface


def _select_fields(surface: Surface, wanted: list[str]) -> Surface:
    """The surface with only the ``wanted`` fields; a name the file does not have is an error."""
    missing = [key for key in wanted if key not in surface.fields]
    if missing:
        raise SurfaceError(
            f"{surface.name}: requested field(s) {missing} not in the file (it has {sorted(surface.fields)})"
        )
    return Surface(
        surface.vertices, surface.faces, surface.normals, {key: surface.fields[key] for key in wanted}, surface.name
    )


# ====================================================================== PLY, OBJ, OFF, STL
def _load_trimesh(name: str, extension: str) -> Surface:
    """Read PLY/OBJ/OFF/STL with trimesh, keeping the file's vertex order."""
    import trimesh  # here, not at start-up

    options = {"maintain_order": True} if extension == ".obj" else {}
    try:
        loaded = trimesh.load(name, process=False, **options)
        if isinstance(loaded, trimesh.Scene) and not any(
            isinstance(geometry, trimesh.PointCloud) for geometry in loaded.geometry.values()
        ):
            # Several meshes in one file: trimesh's own concatenation (applies the scene transforms).
            loaded = trimesh.load(name, process=False, force="mesh", **options)
    except Exception as error:  # trimesh raises many types for a malformed file
        if extension in _TEXT_MESH_EXTENSIONS:
            _check_text_mesh(name, extension)  # names the bad face and its line, or says "not text"
        raise SurfaceError(f"{name}: cannot read the file: {type(error).__name__}: {error}") from error
    if extension in _TEXT_MESH_EXTENSIONS and len(getattr(loaded, "vertices", ())) == 0:
        _check_text_mesh(name, extension)  # a binary or non-UTF-8 file reads as "no vertices": say unreadable

    if extension == ".ply":
        _check_ply_counts(name, loaded)
    raw = loaded.metadata.get("_ply_raw", {}).get("vertex", {}).get("data", {}) if extension == ".ply" else {}
    raw = raw if isinstance(raw, Mapping) else {}
    if isinstance(loaded, trimesh.PointCloud):
        vertices = np.asarray(loaded.vertices, dtype=np.float64)
        normals = None
        if all(key in raw for key in ("nx", "ny", "nz")):
            normals = np.concatenate(
                [np.asarray(raw[key], dtype=np.float64).reshape(-1, 1) for key in ("nx", "ny", "nz")], axis=1
            )
        return Surface(vertices, None, normals, _ply_fields(raw, len(vertices)), name)
    if not isinstance(loaded, trimesh.Trimesh):
        raise SurfaceError(f"{name}: the file holds a {type(loaded).__name__}, not a mesh or a point cloud")

    vertices = np.asarray(loaded.vertices, dtype=np.float64)
    faces = np.asarray(loaded.faces, dtype=np.int64)
    if extension == ".stl":
        vertices, faces, _, _ = merge_coincident(vertices, faces, None, {})
    # File normals of a mesh are not kept: the face orientation defines the normals (vertex_normals()).
    return Surface(vertices, faces, None, _ply_fields(raw, len(vertices)), name)


def _check_text_mesh(name: str, extension: str) -> None:
    """Explain why a text mesh (OBJ, OFF) could not be read: a SurfaceError for a file that is not UTF-8
    text, or for the first face whose vertex index is out of range (with its 1-based line); returns if
    neither applies."""
    with open(name, "rb") as handle:
        data = handle.read()
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as error:
        text = None
        where = error.start
    if text is None or "\x00" in text:
        where = data.find(b"\x00") if text is not None else where
        raise SurfaceError(
            f"{name}: unreadable: not a text {extension[1:].upper()} file (binary or not UTF-8 at byte {where})"
        )
    lines = text.splitlines()
    faces = _obj_faces(lines) if extension == ".obj" else _off_faces(lines)
    if faces is None:
        return
    n_vertices, entries, base = faces
    for face_number, (line_number, indices) in enumerate(entries):
        for index in indices:
            resolved = index + n_vertices if (base == 1 and index < 0) else index - base
            if not 0 <= resolved < n_vertices:
                raise SurfaceError(
                    f"{name}: face {face_number} (line {line_number}) refers to vertex {index}, but "
                    f"the file has {n_vertices} vertices ({'1' if base else '0'}-based indices)"
                )


def _obj_faces(lines: list[str]):
    """(vertex count, [(line, vertex indices of a face)], index base 1) of OBJ text; None if unparsable."""
    n_vertices, entries = 0, []
    for line_number, line in enumerate(lines, start=1):
        parts = line.split("#", 1)[0].split()
        if not parts:
            continue
        if parts[0] == "v":
            n_vertices += 1
        elif parts[0] == "f":
            try:
                entries.append((line_number, [int(token.split("/")[0]) for token in parts[1:]]))
            except ValueError:
                return None
    return n_vertices, entries, 1


def _off_faces(lines: list[str]):
    """(vertex count, [(line, vertex indices of a face)], index base 0) of OFF text; None if unparsable."""
    content = [(number, line.split("#", 1)[0].split()) for number, line in enumerate(lines, start=1)]
    content = [(number, parts) for number, parts in content if parts]
    if not content:
        return None
    if content[0][1][0].upper().endswith("OFF"):
        head = content[0][1][1:]
        content = content[1:] if not head else [(content[0][0], head)] + content[1:]
    try:
        n_vertices, n_faces = int(content[0][1][0]), int(content[0][1][1])
        rows = content[1 + n_vertices : 1 + n_vertices + n_faces]
        entries = [(number, [int(v) for v in parts[1 : 1 + int(parts[0])]]) for number, parts in rows]
    except (ValueError, IndexError):
        return None
    return n_vertices, entries, 0


def _check_ply_counts(name: str, loaded) -> None:
    """Compare what trimesh read with the element counts the PLY header declares.

    trimesh silently returns a point cloud (faces dropped) or fewer elements for a truncated PLY; a file
    that is shorter than its header says is an error, never a partial mesh.
    """
    with open(name, "rb") as handle:
        head = handle.read(65536)
    end = head.find(b"end_header")
    if end < 0:
        return  # trimesh read it without a header in the first 64 KiB: nothing to compare against
    declared = {}
    for line in head[:end].decode("ascii", errors="replace").splitlines():
        parts = line.split()
        if len(parts) == 3 and parts[0] == "element" and parts[2].isdigit():
            declared[parts[1]] = int(parts[2])
    n_vertices = len(getattr(loaded, "vertices", ()))
    faces = getattr(loaded, "faces", None)
    n_faces = 0 if faces is None else len(faces)
    want_vertices, want_faces = declared.get("vertex"), declared.get("face", 0)
    # Polygons are split into triangles, so a mesh may hold more triangles than the header's faces.
    if (want_vertices is not None and n_vertices != want_vertices) or n_faces < want_faces:
        raise SurfaceError(
            f"{name}: the header declares {want_vertices} vertices and {want_faces} faces but only {n_vertices} "
            f"vertices and {n_faces} faces could be read (truncated or corrupt file?)"
        )


def _ply_fields(raw: Mapping, n_vertices: int) -> dict[str, np.ndarray]:
    """Per-vertex PLY properties other than position, normal and colour: (N,) float64 arrays (or (N, C)
    for list properties of fixed length)."""
    fields = {}
    for key, values in raw.items():
        values = np.asarray(values)
        if key in _PLY_NON_FIELDS or values.dtype == object or len(values) != n_vertices:
            continue
        values = values.astype(np.float64).reshape(n_vertices, -1)
        fields[key] = values[:, 0] if values.shape[1] == 1 else values
    return fields


# ====================================================================== MATLAB
def _load_mat(name: str) -> Surface:
    """Read the authors' MATLAB layout: X (V, 3), F (T, 3) 1-based, per-vertex fields."""
    try:
        content = scipy.io.loadmat(name)
    except NotImplementedError as error:  # MATLAB v7.3 files are HDF5
        raise SurfaceError(f"{name}: MATLAB v7.3 (HDF5) files are not supported; save with -v7: {error}") from error
    except Exception as error:
        raise SurfaceError(f"{name}: cannot read the .mat file: {type(error).__name__}: {error}") from error
    arrays = {key: value for key, value in content.items() if not key.startswith("__")}
    if "X" not in arrays:
        raise SurfaceError(f"{name}: no vertex array 'X' in the .mat file (keys: {sorted(arrays)})")
    vertices = np.asarray(arrays.pop("X"))
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise SurfaceError(f"{name}: 'X' must have shape (V, 3), got {vertices.shape}")
    faces = _mat_faces(name, np.asarray(arrays.pop("F"))) if "F" in arrays else None
    n = vertices.shape[0]
    fields = {}
    for key, value in arrays.items():
        value = np.asarray(value)
        if value.ndim in (1, 2) and value.shape[0] == n and np.issubdtype(value.dtype, np.number):
            fields[key] = value[:, 0] if value.ndim == 2 and value.shape[1] == 1 else value
    return Surface(vertices, faces, None, fields, name)


def _mat_faces(name: str, one_based: np.ndarray) -> np.ndarray:
    """0-based int64 faces from the 1-based ``F`` array of a .mat file, after checking every index."""
    if one_based.ndim != 2 or one_based.shape[1] != 3:
        raise SurfaceError(f"{name}: 'F' must have shape (T, 3), got {one_based.shape}")
    if one_based.dtype.kind not in "biuf":
        raise SurfaceError(f"{name}: 'F' must hold vertex indices (numbers), got {one_based.dtype}")
    if one_based.dtype.kind == "f":
        # MATLAB stores indices as doubles by default; a NaN or 1.5 must not be truncated to an index.
        whole = np.isfinite(one_based) & (one_based == np.round(one_based)) & (np.abs(one_based) < 2.0**53)
        if not whole.all():
            bad = int(np.argwhere(~whole)[0, 0])
            raise SurfaceError(f"{name}: face {bad} = {one_based[bad].tolist()} in 'F' is not a whole vertex index")
    if one_based.size and one_based.min() < 1:
        bad = int(np.argwhere(one_based < 1)[0, 0])
        raise SurfaceError(
            f"{name}: face {bad} = {one_based[bad].tolist()} has an index below 1, but 'F' holds "
            "1-based (MATLAB) vertex indices"
        )
    # uint16 would wrap around on "- 1" for an index of 0; convert first.
    return one_based.astype(np.int64) - 1


# ====================================================================== point cloud arrays
def _load_cloud_array(name: str, extension: str) -> Surface:
    """Read an (N, 3) or (N, 6) array (positions, then normals) from .npy or text."""
    try:
        if extension == ".npy":
            array = np.load(name, allow_pickle=False)
        else:
            array = np.loadtxt(name, dtype=np.float64, comments="#", ndmin=2)
    except Exception as error:
        raise SurfaceError(f"{name}: cannot read the point cloud: {type(error).__name__}: {error}") from error
    array = np.asarray(array)
    if array.ndim != 2 or array.shape[1] not in (3, 6):
        raise SurfaceError(f"{name}: a point cloud array must have shape (N, 3) or (N, 6), got {array.shape}")
    normals = array[:, 3:6] if array.shape[1] == 6 else None
    return Surface(array[:, :3], None, normals, {}, name)
