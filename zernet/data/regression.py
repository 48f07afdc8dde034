"""Scalar-field regression: a per-vertex value to predict on each surface.

Two layouts:

- **Aneurysm** (:func:`load_aneurysm`): the ZerNet authors' MATLAB files ``<root>/TP_Ia<ID>I.mat`` with
  ``X`` (V, 3) positions at area 100, ``F`` (T, 3) 1-based triangles and ``J2m`` (V, 1) finite-element wall
  stress (see the data set's README). Surfaces are kept at area 100; if a different area is forced, the
  stress scales with the square root of the area (area exponent 0.5), as stress of a pressurised thin shell
  scales with its size.
- **Generic** (:func:`load_regression`): meshes (.ply/.obj/.off/.stl) each with a per-vertex value file of
  the same stem (``bunny.ply`` + ``bunny.npy`` or ``bunny.txt``, one value per vertex), or .mat files with a
  named field. The target's area exponent is given by the user (0 for dimensionless values).

Leave-one-out cross-validation over chosen shapes: :func:`leave_one_out_splits` gives one fold's splits for
``dataset.with_splits(...)``.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from functools import partial
from pathlib import Path

import numpy as np

from zernet.data.dataset import DatasetError, ShapeDataset, carve_validation
from zernet.data.options import LoaderOptions
from zernet.data.preprocess import build_dataset
from zernet.data.segmentation import MESH_EXTENSIONS, draw_test_names, find_meshes
from zernet.data.source import ShapeSource, file_key, read_text_numbers
from zernet.geometry import Surface, load_surface
from zernet.operators import PatchConfig

__all__ = [
    "ANEURYSM_AREA",
    "PAPER_CASES",
    "load_aneurysm",
    "load_regression",
    "leave_one_out_splits",
    "aneurysm_patch_configs",
    "read_values",
    "load_mat_field",
    "load_mesh_values",
]

ANEURYSM_AREA = 100.0
#: The five held-out cases of the paper's Table 3.
PAPER_CASES = ("TP_Ia105I", "TP_Ia166I", "TP_Ia182I", "TP_Ia32I", "TP_Ia33I")
VALUE_EXTENSIONS = (".npy", ".txt")


def aneurysm_patch_configs(n_scales: int = 1, **overrides):
    """Patch settings for the aneurysms at area 100, same relative patch size and sampling density as the
    paper's FAUST setting: r0 = 5.5 · sqrt(100 / 15000) ≈ 0.45 (a disk covers 0.63 % of the surface) and
    12000 samples per surface, so a disk holds ~76 samples of which ``patch_size = 50`` are fitted.
    Scale s has radius 0.45 · 2**s. ``overrides`` go to every PatchConfig."""
    settings = {"n_samples": 12000, "patch_size": 50}
    settings.update(overrides)
    return [PatchConfig(r0=0.45 * 2**s, **settings) for s in range(n_scales)]


#: Largest magnitude accepted for a regression value: the training loop standardises targets with sums of
#: squares, which overflow float64 beyond about 1e154.
MAX_VALUE = 1e150


def read_values(path: str | os.PathLike) -> np.ndarray:
    """Per-vertex values from a .npy file or a text file (one per line), as (L,) float64."""
    path = Path(path)
    lines = None
    if path.suffix.lower() == ".npy":
        try:
            values = np.load(path, allow_pickle=False)
        except Exception as error:
            raise DatasetError(f"{path}: cannot read values: {type(error).__name__}: {error}") from None
    else:
        values, lines = read_text_numbers(path, "value")
    if np.asarray(values).dtype.kind not in "biuf":
        raise DatasetError(f"{path}: values must be numbers, got an array of {np.asarray(values).dtype}")
    values = np.asarray(values, dtype=np.float64)
    if values.ndim == 2 and values.shape[1] == 1:
        values = values[:, 0]
    if values.ndim != 1:
        raise DatasetError(f"{path}: expected one value per vertex (a 1-D array), got shape {values.shape}")
    if not np.all(np.isfinite(values)):
        bad = int(np.flatnonzero(~np.isfinite(values))[0])
        where = f"line {lines[bad]}" if lines is not None and values.ndim == 1 else f"entry {bad}"
        raise DatasetError(f"{path}: {where}: value {values[bad]} is not finite; targets must be finite")
    if values.size and np.abs(values).max() > MAX_VALUE:
        bad = int(np.argmax(np.abs(values)))
        raise DatasetError(
            f"{path}: value {bad} is {values[bad]}; values beyond ±{MAX_VALUE:g} overflow the "
            "target statistics (their squares exceed float64): rescale the file"
        )
    return values


def load_mat_field(path: str, field: str) -> tuple[Surface, np.ndarray]:
    """ShapeSource loader: a .mat surface and its named per-vertex field (removed from the surface)."""
    surface = load_surface(path)
    if field not in surface.fields:
        raise DatasetError(f"{path}: no per-vertex field {field!r} (it has {sorted(surface.fields) or 'none'})")
    target = np.asarray(surface.fields[field], dtype=np.float64)
    if target.ndim != 1:
        raise DatasetError(f"{path}: field {field!r} has shape {target.shape}; expected one value per vertex")
    fields = {k: v for k, v in surface.fields.items() if k != field}
    return Surface(surface.vertices, surface.faces, surface.normals, fields, surface.name), target


def load_mesh_values(mesh_path: str, value_path: str) -> tuple[Surface, np.ndarray]:
    """ShapeSource loader: a mesh and the per-vertex values of its companion file."""
    surface = load_surface(mesh_path)
    values = read_values(value_path)
    if len(values) != surface.n_vertices:
        raise DatasetError(
            f"{value_path}: has {len(values)} values but {mesh_path} has {surface.n_vertices} "
            "vertices (one value per vertex expected)"
        )
    return surface, values


def leave_one_out_splits(
    names: Sequence[str], held_out: str, n_val: int | float = 2, seed: int = 0
) -> dict[str, list[int]]:
    """Splits of one leave-one-out fold: test = ``held_out``, val = ``n_val`` seeded shapes of the others,
    train = the rest. Indices refer to ``names`` (use ``dataset.names``); apply with ``dataset.with_splits``.
    """
    names = list(names)
    if held_out not in names:
        raise DatasetError(f"leave-one-out: {held_out!r} is not a shape of the data set (e.g. {names[:3]})")
    test = names.index(held_out)
    train, val = carve_validation([i for i in range(len(names)) if i != test], n_val, seed)
    return {"train": train, "val": val, "test": [test]}


def _splits_for(names: list[str], test: Sequence[str] | str | None, where: Path) -> dict[str, list[str]]:
    if test is None:
        return {"train": list(names), "test": []}
    test = [test] if isinstance(test, str) else [str(t) for t in test]
    unknown = sorted(set(test) - set(names))
    if unknown:
        raise DatasetError(f"{where}: test shapes {unknown[:5]} not found (names are file stems, e.g. {names[0]!r})")
    return {"train": [n for n in names if n not in set(test)], "test": test}


def load_aneurysm(
    root: str | os.PathLike,
    field: str = "J2m",
    test: Sequence[str] | str | None = None,
    area: float | None = ANEURYSM_AREA,
    options: LoaderOptions = LoaderOptions(),
) -> ShapeDataset:
    """The aneurysm wall-stress data set: every ``*.mat`` file under ``root`` (not recursive).

    ``field``: the target (default J2m), area exponent 0.5. ``test``: held-out case name(s) (e.g.
    "TP_Ia105I"); default none (use :func:`leave_one_out_splits` for the paper's folds). ``area``: target
    surface area (default 100, the files' own; None keeps the files' scale). ``options``: the shared
    :class:`~zernet.data.options.LoaderOptions`; the aneurysm defaults are ``patch_configs``
    :func:`aneurysm_patch_configs` and ``n_val`` 2.
    """
    options = options.with_defaults(n_val=2, patch_configs=aneurysm_patch_configs())
    root = Path(os.path.expanduser(os.fspath(root)))
    if not root.is_dir():
        raise DatasetError(
            f"aneurysm folder {root} does not exist"
            if not root.exists()
            else f"aneurysm root {root} is a file; give the folder holding the TP_Ia*I.mat files"
        )
    files = sorted(root.glob("*.mat"))
    if not files:
        raise DatasetError(f"{root}: no .mat files; expected the authors' layout TP_Ia<ID>I.mat (X, F, {field})")
    sources = [
        ShapeSource(
            name=path.stem,
            load=partial(load_mat_field, str(path), field),
            key=file_key(path) + f"|{field}",
            target_exponent=0.5,
        )
        for path in files
    ]
    names = [s.name for s in sources]
    return build_dataset(
        sources,
        target_area=area,
        task="regression",
        num_classes=None,
        split_names=_splits_for(names, test, root),
        info={
            "kind": "aneurysm",
            "root": str(root),
            "field": field,
            "paper_cases": list(PAPER_CASES),
            "target_exponent": 0.5,
        },
        **options.build_arguments(),
    )


def load_regression(
    root: str | os.PathLike,
    field: str | None = None,
    target_exponent: float = 0.0,
    test: Sequence[str] | str | None = None,
    test_fraction: float | None = None,
    area: float | None = None,
    options: LoaderOptions = LoaderOptions(),
) -> ShapeDataset:
    """A generic per-vertex regression data set from the folder ``root`` (recursive).

    Each mesh ``<stem>.ply|.obj|.off|.stl`` needs ``<stem>.npy`` or ``<stem>.txt`` beside it; each ``.mat``
    file needs ``field`` (its named per-vertex array). ``target_exponent``: the target's area exponent.
    ``test``: names (paths relative to root, without extension) of the test shapes, or ``test_fraction`` for
    a share drawn with ``options.seed``; neither: no test split. ``area``: target area (default None keeps
    the files' scale). ``options``: the shared :class:`~zernet.data.options.LoaderOptions`;
    ``options.patch_configs`` is required (no default suits every scale), ``n_val`` defaults to 0.1.
    """
    options = options.with_defaults(n_val=0.1)
    root = Path(os.path.expanduser(os.fspath(root)))
    if not root.is_dir():
        raise DatasetError(
            f"regression folder {root} does not exist"
            if not root.exists()
            else f"regression root {root} is a file; give the folder of meshes and value files"
        )
    if options.patch_operators and not options.patch_configs:
        raise DatasetError("regression: give patch_configs (a patch radius suited to the surfaces' area)")
    sources, missing = [], []
    for path in find_meshes(root, MESH_EXTENSIONS + (".mat",)):
        name = str(path.relative_to(root).with_suffix(""))
        if path.suffix.lower() == ".mat":
            if field is None:
                raise DatasetError(f"{path}: .mat files need field= (the name of the per-vertex target array)")
            sources.append(
                ShapeSource(
                    name, partial(load_mat_field, str(path), field), file_key(path) + f"|{field}", target_exponent
                )
            )
            continue
        companions = [path.with_suffix(ext) for ext in VALUE_EXTENSIONS if path.with_suffix(ext).is_file()]
        if not companions:
            missing.append(str(path.relative_to(root)))
            continue
        sources.append(
            ShapeSource(
                name,
                partial(load_mesh_values, str(path), str(companions[0])),
                file_key(path, companions[0]),
                target_exponent,
            )
        )
    if missing:
        shown = ", ".join(missing[:8]) + (f" and {len(missing) - 8} more" if len(missing) > 8 else "")
        raise DatasetError(
            f"{root}: no per-vertex value file (<stem>.npy or <stem>.txt) for {len(missing)} mesh(es): {shown}"
        )
    if not sources:
        raise DatasetError(f"{root}: no meshes ({', '.join(MESH_EXTENSIONS)}) or .mat files found")
    names = [s.name for s in sources]
    if test is None and test_fraction is not None:
        test = draw_test_names(names, test_fraction, options.seed)
    return build_dataset(
        sources,
        target_area=area,
        task="regression",
        num_classes=None,
        split_names=_splits_for(names, test, root),
        info={"kind": "regression", "root": str(root), "field": field, "target_exponent": target_exponent},
        **options.build_arguments(),
    )
