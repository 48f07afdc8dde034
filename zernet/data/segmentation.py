"""Part segmentation: meshes with per-vertex or per-face labels.

Two layouts, both handled by :func:`load_segmentation`:

1. **One label file per mesh** with the same stem: ``meshes/<rel>/<stem>.ply`` (or .obj/.off/.stl) and
   ``labels/<rel>/<stem>.txt`` (or ``.npy``, or ``.seg``/``.eseg``), where ``labels`` may be the mesh folder
   itself. This is the layout of the human-segmentation benchmark of Maron et al. 2017 for its non-FAUST
   parts (``meshes/train/adobe/...``, ``segs/train/adobe/...``): meshes and their per-face label files.
2. **One label file shared by same-topology meshes**: ``labels`` is a single text file (e.g. the
   benchmark's ``faust_corrected.txt`` / ``faust_seg.txt``) with one label per line, used for every mesh —
   the benchmark's FAUST meshes all share one connectivity, so one per-face labelling serves all of them.

Label files hold one integer per line (text, whitespace-separated also accepted) or a 1-D .npy array.

Per-vertex or per-face is decided by the count: N values for N vertices = per vertex, F values for F faces =
per face (``label_kind`` forces one when N == F). Anything else is an error naming the label file, the mesh
and all three counts.

**Per-face -> per-vertex rule**: each vertex takes the label with the largest total area among its incident
faces (area-weighted majority vote); an exact tie goes to the smallest label. A vertex used by no face
gets label 0.

**0- or 1-based labels** (``label_base="auto"``): the benchmark's files number the 8 parts 1..8. Over all
label files of the data set: if no file contains 0 and some file contains ``num_classes``, the labels are
1-based and 1 is subtracted; otherwise they are 0-based. After that every label must lie in
0..num_classes-1, or the error names the file and the offending value. The detected base is stored in
``dataset.info["label_base"]``. Pass ``label_base=0`` or ``1`` to skip the detection.

Class names (legends, per-class scores): ``class_names`` if given, else the lines of ``class_names.txt`` beside
the labels, else "part 1" .. "part N" (:func:`resolve_class_names`). They are never inferred from the number
of classes: data sets with 8 parts number them in different orders.

A label file that cannot be read (text where a number should be, reported with its 1-based line) fails its
own mesh only, which the bad-shape policy (``LoaderOptions.on_error``) then handles like any other.

Test split: mesh paths with a folder called ``test`` (the benchmark's ``meshes/test/shrec``) form the test
split when there are any; otherwise ``test`` names them, or a seeded ``test_fraction`` of the meshes is used.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import replace
from functools import partial
from pathlib import Path

import numpy as np

from zernet.data.dataset import DatasetError, ShapeDataset
from zernet.data.options import LoaderOptions
from zernet.data.preprocess import build_dataset
from zernet.data.source import ShapeSource, file_key, read_text_numbers
from zernet.geometry import Surface, load_surface, validate_surface

__all__ = [
    "MESH_EXTENSIONS",
    "LABEL_EXTENSIONS",
    "HUMAN_PART_NAMES",
    "load_segmentation",
    "read_labels",
    "face_to_vertex_labels",
    "find_meshes",
    "load_labelled_mesh",
    "draw_test_names",
    "resolve_class_names",
    "CLASS_NAMES_FILE",
]

MESH_EXTENSIONS = (".ply", ".obj", ".off", ".stl")
LABEL_EXTENSIONS = (".txt", ".npy", ".seg", ".eseg", ".labels")
#: The file beside the labels that names the classes, one per line in label order.
CLASS_NAMES_FILE = "class_names.txt"
#: The 8 parts of Maron et al. 2017's human-segmentation benchmark, in its label order (label 1 = head).
HUMAN_PART_NAMES = ("head", "torso", "upper arm", "lower arm", "hand", "upper leg", "lower leg", "foot")


def find_meshes(root: Path, extensions: Sequence[str] = MESH_EXTENSIONS) -> list[Path]:
    """Mesh files under ``root`` (recursive, sorted)."""
    return sorted(p for p in root.rglob("*") if p.is_file() and p.suffix.lower() in extensions)


def read_labels(path: str | os.PathLike) -> np.ndarray:
    """Integer labels from a text file (one per line or whitespace-separated) or a .npy file: (L,) int64.

    A bad value is reported with the file and, for text, its 1-based line."""
    path = Path(path)
    lines = None
    if path.suffix.lower() == ".npy":
        try:
            values = np.load(path, allow_pickle=False)
        except Exception as error:
            raise DatasetError(f"{path}: cannot read labels: {type(error).__name__}: {error}") from None
    else:
        values, lines = read_text_numbers(path, "label")
    values = np.asarray(values).reshape(-1)
    if values.size == 0:
        raise DatasetError(f"{path}: label file is empty")
    if values.dtype.kind not in "biuf":
        raise DatasetError(f"{path}: labels must be numbers, got an array of {values.dtype}")
    values = values.astype(np.float64)  # exact for every label a data set can have (|label| < 2**53)
    # Beyond 2**53 a float is no longer an exact integer and int64 conversion would wrap: not a label.
    bad_mask = ~np.isfinite(values) | (values != np.round(values)) | (np.abs(values) >= 2.0**53)
    if bad_mask.any():
        bad = int(np.flatnonzero(bad_mask)[0])
        where = f"line {lines[bad]}" if lines is not None else f"entry {bad}"
        raise DatasetError(f"{path}: {where}: label {float(values[bad])!r} is not an integer class label")
    return values.astype(np.int64)


def face_to_vertex_labels(
    faces: np.ndarray, face_labels: np.ndarray, face_areas: np.ndarray, n_vertices: int
) -> np.ndarray:
    """Per-vertex labels by the area-weighted majority of the incident faces (ties: smallest label).

    faces (F, 3), face_labels (F,) >= 0, face_areas (F,). Returns (n_vertices,) int64; vertices used by no
    face get 0.
    """
    n_labels = int(face_labels.max()) + 1
    votes = np.zeros((n_vertices, n_labels))
    for corner in range(3):
        np.add.at(votes, (faces[:, corner], face_labels), face_areas)
    # argmax returns the first (smallest) label among equal maxima.
    return votes.argmax(axis=1).astype(np.int64)


def _resolve_labels(
    mesh_path: Path, surface: Surface, raw: np.ndarray, label_path: Path, label_kind: str, base: int, num_classes: int
) -> np.ndarray:
    """Labels of one mesh as per-vertex classes 0..num_classes-1, with the errors of the module docstring."""
    n, f = surface.n_vertices, surface.n_faces
    count = len(raw)
    if label_kind == "vertex" or (label_kind == "auto" and count == n):
        if count != n:
            raise DatasetError(
                f"{label_path}: has {count} labels but {mesh_path} has {n} vertices "
                "(label_kind='vertex' needs one label per vertex)"
            )
        kind = "vertex"
    elif label_kind == "face" or (label_kind == "auto" and count == f):
        if count != f:
            raise DatasetError(
                f"{label_path}: has {count} labels but {mesh_path} has {f} faces "
                "(label_kind='face' needs one label per face)"
            )
        kind = "face"
    else:
        raise DatasetError(
            f"{label_path}: has {count} labels but {mesh_path} has {n} vertices and {f} faces; "
            "expected one label per vertex or one per face"
        )
    labels = raw - base
    if labels.min() < 0 or labels.max() >= num_classes:
        bad = labels.min() if labels.min() < 0 else labels.max()
        raise DatasetError(
            f"{label_path}: label {bad + base} is outside the {num_classes} classes "
            f"({base}..{num_classes - 1 + base} with {base}-based labels)"
        )
    if kind == "face":
        labels = face_to_vertex_labels(surface.faces, labels, surface.face_areas(), n)
    return labels


def load_labelled_mesh(
    mesh_path: str, label_path: str, label_kind: str, base: int, num_classes: int, repair: bool
) -> tuple[Surface, np.ndarray]:
    """ShapeSource loader: the mesh and its per-vertex labels.

    Without repair, the mesh is read and validated by :func:`~zernet.geometry.io.load_surface`. With repair,
    the labels are resolved on the mesh exactly as stored (a repair drops faces and merges vertices, which
    would break the order a label file refers to) and the repair is applied afterwards, the per-vertex
    labels following the merged vertices.
    """
    if not repair:
        surface = load_surface(mesh_path)
    else:
        surface = _read_as_stored(mesh_path)
    labels = _resolve_labels(
        Path(mesh_path), surface, read_labels(label_path), Path(label_path), label_kind, base, num_classes
    )
    if repair:
        labelled = validate_surface(surface.with_fields({"__labels__": labels}), repair=True)
        labels = np.asarray(labelled.fields["__labels__"]).astype(np.int64)
        fields = {k: v for k, v in labelled.fields.items() if k != "__labels__"}
        surface = Surface(labelled.vertices, labelled.faces, labelled.normals, fields, labelled.name)
    return surface, labels


def _read_as_stored(mesh_path: str) -> Surface:
    """A mesh exactly as stored (vertex and face order kept, no validation yet)."""
    import trimesh  # here, not at start-up

    options = {"maintain_order": True} if mesh_path.lower().endswith(".obj") else {}
    try:
        mesh = trimesh.load(mesh_path, process=False, force="mesh", **options)
    except Exception as error:
        raise DatasetError(f"{mesh_path}: cannot read the mesh: {type(error).__name__}: {error}") from error
    faces = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))))
    if len(faces) == 0:
        raise DatasetError(f"{mesh_path}: has no faces; segmentation needs triangle meshes")
    return Surface(np.asarray(mesh.vertices), faces, name=mesh_path)


def _label_file_for(mesh: Path, mesh_root: Path, label_root: Path) -> Path | None:
    """The label file of ``mesh``: same relative folder and stem under ``label_root``, or the same stem
    anywhere under it when unique (the benchmark keeps ``segs/train/adobe/x.txt`` for
    ``meshes/train/adobe/x.off``)."""
    relative = mesh.relative_to(mesh_root).with_suffix("")
    for extension in LABEL_EXTENSIONS:
        candidate = label_root / relative.parent / (relative.name + extension)
        if candidate.is_file() and candidate != mesh:
            return candidate
    matches = [p for p in label_root.rglob(mesh.stem + ".*") if p.suffix.lower() in LABEL_EXTENSIONS]
    return matches[0] if len(matches) == 1 else None


def _pair_with_labels(mesh_files: list[Path], mesh_root: Path, label_root: Path) -> list[tuple[Path, Path]]:
    """Every mesh with its label file; DatasetError listing the meshes that have none."""
    pairs: list[tuple[Path, Path]] = []
    unlabelled = []
    for mesh in mesh_files:
        label = label_root if label_root.is_file() else _label_file_for(mesh, mesh_root, label_root)
        if label is None:
            unlabelled.append(str(mesh.relative_to(mesh_root)))
        else:
            pairs.append((mesh, label))
    if unlabelled:
        shown = ", ".join(unlabelled[:8]) + (f" and {len(unlabelled) - 8} more" if len(unlabelled) > 8 else "")
        raise DatasetError(
            f"{label_root}: no label file (same name, {'/'.join(LABEL_EXTENSIONS)}) for "
            f"{len(unlabelled)} mesh(es): {shown}"
        )
    return pairs


def _label_base(label_files: set[Path], label_base: int | str, num_classes: int) -> int:
    """The labels' base (0 or 1), decided once over all label files (see the module docstring).

    A label file that cannot be read is left out of the decision here: its mesh then fails in the
    preprocessing with the same message and is handled like any other bad shape (``on_error``)."""
    label_values = []
    for label in sorted(label_files):
        try:
            label_values.append(read_labels(label))
        except DatasetError:
            continue
    if label_base in (0, 1):
        return int(label_base)
    if label_base != "auto":
        raise DatasetError(f"label_base must be 'auto', 0 or 1, got {label_base!r}")
    has_zero = any((values == 0).any() for values in label_values)
    has_top = any((values == num_classes).any() for values in label_values)
    return 1 if (not has_zero and has_top) else 0


def resolve_class_names(class_names: Sequence[str] | None, num_classes: int, label_root: Path) -> list[str]:
    """The class names: ``class_names`` if given, else ``class_names.txt`` beside the labels, else
    "part 1" .. "part N"; a list of another length than ``num_classes`` is an error naming its source."""
    source = "data.class_names"
    if class_names is None:
        names_file = (label_root.parent if label_root.is_file() else label_root) / CLASS_NAMES_FILE
        if not names_file.is_file():
            return [f"part {i + 1}" for i in range(num_classes)]
        try:
            text = names_file.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as error:
            raise DatasetError(f"{names_file}: cannot read the class names ({error})") from None
        class_names = [line.strip() for line in text.splitlines() if line.strip()]
        source = str(names_file)
    if isinstance(class_names, str) or not all(isinstance(name, str) for name in class_names):
        raise DatasetError(f"{source}: class names must be a list of strings, got {class_names!r}")
    if len(class_names) != num_classes:
        raise DatasetError(
            f"{source}: {len(class_names)} class names for {num_classes} classes "
            "(data.num_classes); give one name per class, in label order"
        )
    return list(class_names)


def draw_test_names(names: Sequence[str], test_fraction: float, seed: int) -> list[str]:
    """A seeded share ``test_fraction`` of ``names`` (at least one, and at least one left), in name order."""
    if not 0 < test_fraction < 1:
        raise DatasetError(f"test_fraction must be in (0, 1), got {test_fraction}")
    count = min(len(names) - 1, max(1, int(round(test_fraction * len(names)))))
    order = np.random.default_rng(seed + 7919).permutation(len(names))
    return [names[i] for i in sorted(order[:count])]


def _test_names(
    names: list[str], test: Sequence[str] | None, test_fraction: float, seed: int, mesh_root: Path
) -> list[str]:
    """The test meshes: ``test`` if given, else those under a ``test`` folder, else a seeded share."""
    if test is not None:
        test_names = [str(t) for t in test]
        unknown = sorted(set(test_names) - set(names))
        if unknown:
            raise DatasetError(
                f"{mesh_root}: test meshes {unknown[:5]} not found (names are paths relative to "
                f"the mesh folder without extension, e.g. {names[0]!r})"
            )
        return test_names
    if any("test" in Path(name).parts[:-1] for name in names):
        return [name for name in names if "test" in Path(name).parts[:-1]]
    return draw_test_names(names, test_fraction, seed)


def load_segmentation(
    meshes: str | os.PathLike,
    labels: str | os.PathLike | None = None,
    num_classes: int = 8,
    class_names: Sequence[str] | None = None,
    label_base: int | str = "auto",
    label_kind: str = "auto",
    test: Sequence[str] | None = None,
    test_fraction: float = 0.2,
    area: float | None = 15000.0,
    options: LoaderOptions = LoaderOptions(),
) -> ShapeDataset:
    """A part-segmentation data set (per-vertex classification).

    Args:
        meshes: folder of meshes (searched recursively) or a single mesh file.
        labels: folder of per-mesh label files, or one label file shared by every mesh; default: the mesh
            folder (label files next to the meshes).
        num_classes: number of parts (8 for the human benchmark).
        class_names: the name of each class, in label order, for legends and per-class scores; default:
            the lines of a ``class_names.txt`` beside the labels (in the label folder, or in the folder of
            a shared label file; ``zernet bodies`` writes one), else "part 1" .. "part N". Names are never
            guessed from the number of classes: label orders differ between data sets.
        label_base: "auto" (see the module docstring), 0 or 1.
        label_kind: "auto", "vertex" or "face".
        test: names (mesh paths relative to ``meshes``, without extension) of the test meshes; default: meshes
            under a ``test`` folder, else a ``test_fraction`` drawn with ``options.seed``.
        area: target surface area (default 15000, human bodies as in the paper; None keeps the files').
        options: the shared :class:`~zernet.data.options.LoaderOptions`. ``options.patch_configs`` is
            required (segmentation data comes at any scale; for human bodies at area 15000 use
            :func:`zernet.data.faust.faust_patch_configs`); ``n_val`` defaults to 0.1; ``on_error`` says whether a
            mesh that fails (unreadable, bad labels, ...) stops the loader (``"raise"``, the default, after
            every mesh was tried) or is left out (``"skip"``); ``repair`` merges duplicate vertices and
            drops degenerate faces after the labels are read, the labels following.
    """
    options = options.with_defaults(n_val=0.1)
    mesh_root = Path(os.path.expanduser(os.fspath(meshes)))
    if not mesh_root.exists():
        raise DatasetError(f"segmentation meshes: {mesh_root} does not exist")
    mesh_files = [mesh_root] if mesh_root.is_file() else find_meshes(mesh_root)
    if mesh_root.is_file():
        mesh_root = mesh_root.parent
    if not mesh_files:
        raise DatasetError(f"{mesh_root}: no mesh files ({', '.join(MESH_EXTENSIONS)}) found")
    label_root = Path(os.path.expanduser(os.fspath(labels))) if labels is not None else mesh_root
    if not label_root.exists():
        raise DatasetError(f"segmentation labels: {label_root} does not exist")
    if label_kind not in ("auto", "vertex", "face"):
        raise DatasetError(f"label_kind must be 'auto', 'vertex' or 'face', got {label_kind!r}")

    pairs = _pair_with_labels(mesh_files, mesh_root, label_root)
    base = _label_base({label for _, label in pairs}, label_base, num_classes)

    names = [str(mesh.relative_to(mesh_root).with_suffix("")) for mesh, _ in pairs]
    sources = [
        ShapeSource(
            name=name,
            load=partial(load_labelled_mesh, str(mesh), str(label), label_kind, base, num_classes, options.repair),
            key=file_key(mesh, label) + f"|{label_kind}|{base}|{num_classes}|{options.repair}",
        )
        for name, (mesh, label) in zip(names, pairs)
    ]

    test_names = _test_names(names, test, test_fraction, options.seed, mesh_root)
    train_names = [name for name in names if name not in set(test_names)]
    class_names = resolve_class_names(class_names, num_classes, label_root)

    if options.patch_operators and not options.patch_configs:
        raise DatasetError("segmentation: give patch_configs (e.g. [{'r0': 5.5}] for human bodies at area 15000)")
    # The shape loader repairs (so the labels follow the merged vertices); the pipeline must not repair again.
    return build_dataset(
        sources,
        target_area=area,
        task="classification",
        num_classes=num_classes,
        split_names={"train": train_names, "test": test_names},
        info={
            "kind": "segmentation",
            "meshes": str(mesh_root),
            "labels": str(label_root),
            "label_base": base,
            "class_names": class_names,
        },
        **replace(options, repair=False).build_arguments(),
    )
