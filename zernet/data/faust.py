"""FAUST correspondence from the user's copy of the data set, in its official layout.

    <root>/MPI-FAUST/training/registrations/tr_reg_000.ply ... tr_reg_099.ply

``root`` may also point at the ``MPI-FAUST`` folder or directly at the ``registrations`` folder. The 100
registrations share one connectivity (6890 vertices, 13776 faces), so the class of a vertex is its index:
correspondence is 6890-way vertex classification. Standard split: 000-079 train (a seeded validation subset
is carved from them), 080-099 test. Surfaces are scaled to area 15000 (the authors' setting, which their
patch radius 5.5 assumes).

Errors name the folder or file: the layout is not found, files are missing (all listed), a mesh has the
wrong vertex count, or a mesh's connectivity differs from ``tr_reg_<first>.ply`` (its vertex indices then do
not correspond, and training on it would teach wrong labels).
"""

from __future__ import annotations

import hashlib
import operator
import os
from collections.abc import Sequence
from functools import partial
from pathlib import Path

import numpy as np

from zernet.data.dataset import DatasetError, ShapeDataset
from zernet.data.options import LoaderOptions
from zernet.data.preprocess import build_dataset
from zernet.data.source import ShapeSource, file_key
from zernet.geometry import Surface, load_surface
from zernet.operators import PatchConfig

__all__ = [
    "FAUST_AREA",
    "FAUST_VERTICES",
    "load_faust",
    "registration_numbers",
    "find_registrations",
    "faust_patch_configs",
]

FAUST_AREA = 15000.0
FAUST_VERTICES = 6890
_PATTERN = "tr_reg_{:03d}.ply"


def faust_patch_configs(n_scales: int = 1, **overrides):
    """The shipped FAUST recipe at area 15000 (``configs/faust_single_scale.yaml``): r0 = 5.5 (then 11, 22
    for more scales), 12000 samples, every sample within r0 fitted except those closer than r0/4
    (``inner_radius``), centre value subtracted, fit ridge 1e-2, front geodesics. The authors fitted the 50
    nearest samples: pass ``patch_size=50`` for their formulation."""
    settings = {"n_samples": 12000, "subtract_center": True, "ridge": 1.0e-2, "backend": "front"}
    settings.update(overrides)
    return [PatchConfig(**{"r0": 5.5 * 2**s, "inner_radius": 5.5 * 2**s / 4, **settings}) for s in range(n_scales)]


def find_registrations(root: str | os.PathLike) -> Path:
    """The folder holding ``tr_reg_XXX.ply``: ``root`` itself, ``root/training/registrations`` or
    ``root/MPI-FAUST/training/registrations``. Raises DatasetError naming what was looked for."""
    root = Path(os.path.expanduser(os.fspath(root)))
    if not root.exists():
        raise DatasetError(f"FAUST folder {root} does not exist")
    if not root.is_dir():
        raise DatasetError(f"FAUST root {root} is a file; give the folder that contains MPI-FAUST")
    candidates = [root / "MPI-FAUST" / "training" / "registrations", root / "training" / "registrations", root]
    for folder in candidates:
        if folder.is_dir() and any(folder.glob("tr_reg_*.ply")):
            return folder
    raise DatasetError(
        f"{root}: no FAUST registrations found. Expected the official layout "
        f"{root}/MPI-FAUST/training/registrations/tr_reg_000.ply ... tr_reg_099.ply "
        "(or a root pointing at MPI-FAUST or at the registrations folder itself)"
    )


def _faces_digest(faces: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(faces, dtype=np.int64).tobytes()).hexdigest()


def _load_registration(path: str, n_vertices: int, faces_digest: str, reference: str) -> tuple[Surface, np.ndarray]:
    """ShapeSource loader: one registration, checked against the reference connectivity."""
    surface = load_surface(path)
    if surface.n_vertices != n_vertices:
        raise DatasetError(
            f"{path}: has {surface.n_vertices} vertices, but FAUST registrations have "
            f"{n_vertices} (as {reference} does)"
        )
    if surface.faces is None or _faces_digest(surface.faces) != faces_digest:
        raise DatasetError(
            f"{path}: its connectivity (faces) differs from {reference}; FAUST registrations share "
            "one connectivity, and correspondence by vertex index needs it"
        )
    return surface, np.arange(n_vertices, dtype=np.int64)


def registration_numbers(value: Sequence[int] | str, name: str) -> list[int]:
    """The registration numbers ``value`` selects: a list of ints, or ``"START:STOP"`` for START, ..., STOP - 1
    (Python's slice convention, so ``"0:180"`` and ``"180:200"`` split 200 bodies). ``DatasetError`` naming
    ``name`` for anything else."""
    if isinstance(value, str):
        start, colon, stop = value.partition(":")
        if not colon or not start.strip().isdigit() or not stop.strip().isdigit() or int(start) >= int(stop):
            raise DatasetError(
                f"FAUST: {name} {value!r} is not a list of registration numbers or a range "
                f"'START:STOP' with START < STOP (e.g. '0:180')"
            )
        return list(range(int(start), int(stop)))
    if isinstance(value, int):  # e.g. YAML 1.1 reads an unquoted 10:20 as the base-60 number 620
        raise DatasetError(
            f"FAUST: {name} is the number {value}; give a list of registration numbers or a "
            f"quoted range such as '0:180'"
        )
    try:
        numbers = [operator.index(i) for i in value]  # integers only: 1.5 is refused, not truncated
    except TypeError:
        raise DatasetError(
            f"FAUST: {name} must be a list of registration numbers or 'START:STOP', got {value!r}"
        ) from None
    if any(i < 0 for i in numbers):
        raise DatasetError(f"FAUST: {name} has negative registration numbers: {[i for i in numbers if i < 0][:5]}")
    return numbers


def load_faust(
    root: str | os.PathLike,
    train_indices: Sequence[int] = range(0, 80),
    test_indices: Sequence[int] = range(80, 100),
    val_indices: Sequence[int] | None = None,
    n_vertices: int | None = FAUST_VERTICES,
    area: float | None = FAUST_AREA,
    options: LoaderOptions = LoaderOptions(),
) -> ShapeDataset:
    """The FAUST correspondence data set (classification, one class per template vertex).

    Args:
        root: see the module docstring.
        train_indices, test_indices: registration numbers XXX of each split (defaults: the standard split),
            as a list or as ``"START:STOP"`` (``"0:180"``: 0 to 179), see :func:`registration_numbers`.
        val_indices: registration numbers of the validation split (None: ``n_val`` shapes carved at random from
            the training ones). Scan ``XXX`` shows person ``XXX // 10``: ``"60:70"`` validates on person 6, so the
            model is chosen on a person it never saw, not on other poses of its training people. Overlaps
            neither the training nor the test registrations.
        n_vertices: the expected vertex count of every registration (None: take the first file's).
        area: target surface area (default 15000; None keeps the files' scale).
        options: the shared :class:`~zernet.data.options.LoaderOptions`. FAUST's defaults:
            ``patch_configs`` :func:`faust_patch_configs`, ``n_val`` 8 validation shapes carved from the
            training ones. A broken registration stops the loader with ``on_error="raise"`` (the default for
            every data set); with correspondence by vertex index it means a broken copy of the data set.

    Returns a :class:`ShapeDataset` with ``correspondence = True`` and ``num_classes`` = vertex count.
    """
    options = options.with_defaults(n_val=8, patch_configs=faust_patch_configs())
    folder = find_registrations(root)
    train_indices = registration_numbers(train_indices, "train_indices")
    test_indices = registration_numbers(test_indices, "test_indices")
    val_indices = [] if val_indices is None else registration_numbers(val_indices, "val_indices")
    for first, second, names in (
        (train_indices, test_indices, "train and the test"),
        (train_indices, val_indices, "train and the validation"),
        (val_indices, test_indices, "validation and the test"),
    ):
        overlap = sorted(set(first) & set(second))
        if overlap:
            raise DatasetError(f"FAUST: registrations {overlap[:5]} are in both the {names} split")
    wanted = sorted(set(train_indices) | set(test_indices) | set(val_indices))
    if not wanted:
        raise DatasetError("FAUST: no registrations selected (train_indices and test_indices are empty)")
    paths = {i: folder / _PATTERN.format(i) for i in wanted}
    missing = [p.name for p in paths.values() if not p.is_file()]
    if missing:
        shown = ", ".join(missing[:10]) + (f" and {len(missing) - 10} more" if len(missing) > 10 else "")
        raise DatasetError(f"{folder}: {len(missing)} of {len(wanted)} FAUST registrations are missing: {shown}")

    # The first registration is the connectivity reference every other one is checked against.
    reference_path = paths[wanted[0]]
    reference = load_surface(reference_path)
    if reference.faces is None:
        raise DatasetError(f"{reference_path}: has no faces; FAUST registrations are triangle meshes")
    if n_vertices is not None and reference.n_vertices != n_vertices:
        raise DatasetError(
            f"{reference_path}: has {reference.n_vertices} vertices, but FAUST registrations have {n_vertices}"
        )
    count = reference.n_vertices
    digest = _faces_digest(reference.faces)

    split_names = {"train": [paths[i].stem for i in train_indices], "test": [paths[i].stem for i in test_indices]}
    if val_indices:
        split_names["val"] = [paths[i].stem for i in val_indices]
    sources = [
        ShapeSource(
            name=paths[i].stem,
            load=partial(_load_registration, str(paths[i]), count, digest, reference_path.name),
            key=file_key(paths[i]) + f"|faces={digest}",
        )
        for i in wanted
    ]
    return build_dataset(
        sources,
        target_area=area,
        task="classification",
        num_classes=count,
        split_names=split_names,
        correspondence=True,
        info={"kind": "faust", "root": str(folder)},
        **options.build_arguments(),
    )
