"""Model files: one format for every stored model, and the one reader of them.

A model file is a plain dictionary of tensors and plain containers (dicts, lists, strings, numbers), loaded
with ``torch.load(weights_only=True)``, so a crafted file cannot run code, after its zip records are
checked. Three fields say what it is: ``"format": MODEL_FILE_FORMAT``, ``"version": MODEL_FILE_VERSION`` and
``"kind"``, one of :data:`MODEL_KINDS`:

- ``checkpoint``: a training run's checkpoint (:mod:`zernet.training.checkpoint`);
- ``backbone``: the weights a run starts from (``pretrained:NAME``), exported from a run's checkpoint
  (:func:`zernet.training.init_from.export_backbone`), float16;
- ``descriptors``: ``zernet match --descriptors``'s descriptor model (:mod:`zernet.matching.model`);
- ``template``: ``zernet match``'s template model (:mod:`zernet.matching.template`), float16.

The rest of the dictionary is the kind's own. Files written before this format (``"format"`` one of
:data:`OLD_FORMATS`) are read as the kind they held. The files shipped with zernet are in
``zernet/pretrained/`` (:func:`pretrained_path`).
"""

from __future__ import annotations

import importlib.resources
import zipfile
from collections.abc import Sequence
from pathlib import Path

import torch

__all__ = [
    "MODEL_FILE_FORMAT",
    "MODEL_FILE_VERSION",
    "MODEL_KINDS",
    "OLD_FORMATS",
    "model_file",
    "read_model_file",
    "PRETRAINED",
    "pretrained_path",
    "pretrained_names",
    "load_checkpoint",
    "checkpoint_path",
]

MODEL_FILE_FORMAT = "zernet-model"
MODEL_FILE_VERSION = 1
MODEL_KINDS = ("checkpoint", "backbone", "descriptors", "template")
#: The formats of the files written before :data:`MODEL_FILE_FORMAT`, and the kind each held (a backbone
#: was written as a checkpoint without its optimiser).
OLD_FORMATS = {"zernet-checkpoint-1": "checkpoint", "zernet-matching-1": "descriptors", "zernet-template-1": "template"}
#: The folder of the models shipped with zernet.
PRETRAINED = Path(str(importlib.resources.files("zernet") / "pretrained"))


def model_file(kind: str, contents: dict) -> dict:
    """What a model file of ``kind`` holds: ``contents`` with the format, version and kind fields."""
    if kind not in MODEL_KINDS:
        raise ValueError(f"unknown model file kind {kind!r} (known: {', '.join(MODEL_KINDS)})")
    return {"format": MODEL_FILE_FORMAT, "version": MODEL_FILE_VERSION, "kind": kind, **contents}


def read_model_file(path: str | Path, kinds: Sequence[str] = MODEL_KINDS, what: str = "zernet model file") -> dict:
    """The model file at ``path``, loaded safely onto the CPU, with its ``kind`` (also for a file of an old
    format); ``what`` names the expected file in the errors.

    Raises:
        FileNotFoundError: no file there.
        ValueError: unreadable (corrupt, truncated, holding objects ``weights_only`` refuses), not a zernet
            model file, of a newer version, or of a kind not in ``kinds`` (the message says which it is).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what} not found: {path}")
    # torch.load does not check the zip CRCs, so flipped bytes in the stored tensors would load silently as
    # wrong weights: check them first (torch writes them; it costs one read of the file).
    if zipfile.is_zipfile(path):
        try:
            with zipfile.ZipFile(path) as archive:
                damaged = archive.testzip()
        except Exception as error:
            damaged = f"? ({type(error).__name__}: {error})"
        if damaged is not None:
            raise ValueError(
                f"{path}: not a readable {what} (stored record {damaged} fails its CRC check: the file is corrupt)"
            )
    try:
        stored = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # truncated, corrupt, or holding objects weights_only refuses
        raise ValueError(f"{path}: not a readable {what} ({type(error).__name__}: {error})") from None
    stored_format = stored.get("format") if isinstance(stored, dict) else None
    if stored_format in OLD_FORMATS:
        stored = {**stored, "format": MODEL_FILE_FORMAT, "version": 0, "kind": OLD_FORMATS[stored_format]}
    elif stored_format != MODEL_FILE_FORMAT or stored.get("kind") not in MODEL_KINDS:
        raise ValueError(f"{path}: not a {what} (expected format {MODEL_FILE_FORMAT})")
    if int(stored.get("version", 0)) > MODEL_FILE_VERSION:
        raise ValueError(
            f"{path}: a {stored['kind']} file of format version {stored['version']}, newer than this zernet "
            f"reads ({MODEL_FILE_VERSION}): update zernet"
        )
    if stored["kind"] not in kinds:
        raise ValueError(f"{path}: not a {what}: it holds a {stored['kind']} model ({_KIND_NAMES[stored['kind']]})")
    return stored


#: What each kind is, for the errors of a file of another kind than asked for.
_KIND_NAMES = {
    "checkpoint": "a training run's checkpoint",
    "backbone": "weights a run starts from, train.init_from",
    "descriptors": "zernet match --descriptors's descriptor model",
    "template": "zernet match's template model",
}


def pretrained_path(name: str) -> Path:
    """The file of the model shipped with zernet as ``name`` (:data:`PRETRAINED`/NAME.pt)."""
    return PRETRAINED / f"{name}.pt"


def pretrained_names(kinds: Sequence[str] = MODEL_KINDS) -> list[str]:
    """The names of the models shipped with zernet whose kind is one of ``kinds``."""
    return sorted(path.stem for path in PRETRAINED.glob("*.pt") if read_model_file(path)["kind"] in kinds)


def load_checkpoint(path: str | Path) -> dict:
    """A training run's checkpoint, or a backbone exported from one (:func:`read_model_file`)."""
    return read_model_file(path, ("checkpoint", "backbone"), "zernet checkpoint")


def checkpoint_path(run_dir_or_checkpoint: str | Path) -> Path:
    """A run folder means its ``best.pt``; a file is taken as it is."""
    path = Path(run_dir_or_checkpoint)
    if path.is_dir():
        best = path / "best.pt"
        if not best.is_file():
            raise FileNotFoundError(f"{path} holds no best.pt: is it a zernet run folder whose training has run?")
        return best
    return path
