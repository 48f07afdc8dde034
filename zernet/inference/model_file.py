"""Reading model files: a run's checkpoint, safely.

A checkpoint is a plain dictionary of tensors and plain containers, loaded with
``torch.load(weights_only=True)`` (a crafted file cannot run code) after its zip records are checked;
``{"format": CHECKPOINT_FORMAT, ...}`` marks it (written by :mod:`zernet.training.checkpoint`).
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import torch

__all__ = ["CHECKPOINT_FORMAT", "load_checkpoint", "checkpoint_path"]

CHECKPOINT_FORMAT = "zernet-checkpoint-1"


def load_checkpoint(path: str | Path) -> dict:
    """Load a zernet checkpoint safely (``weights_only=True``) onto the CPU, with a clear error if unusable."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint not found: {path}")
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
                f"{path}: not a readable zernet checkpoint (stored record {damaged} fails its CRC "
                "check: the file is corrupt)"
            )
    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # truncated, corrupt, or holding objects weights_only refuses
        raise ValueError(f"{path}: not a readable zernet checkpoint ({type(error).__name__}: {error})") from None
    if not isinstance(checkpoint, dict) or checkpoint.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"{path}: not a zernet checkpoint (expected format {CHECKPOINT_FORMAT})")
    return checkpoint


def checkpoint_path(run_dir_or_checkpoint: str | Path) -> Path:
    """A run folder means its ``best.pt``; a file is taken as it is."""
    path = Path(run_dir_or_checkpoint)
    if path.is_dir():
        best = path / "best.pt"
        if not best.is_file():
            raise FileNotFoundError(f"{path} holds no best.pt: is it a zernet run folder whose training has run?")
        return best
    return path
