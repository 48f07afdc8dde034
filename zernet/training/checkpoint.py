"""Checkpoints: what they hold and how they are written (atomically); read by :mod:`zernet.inference.model_file`.

A checkpoint is a model file of kind ``checkpoint`` (:mod:`zernet.inference.model_file`): a plain
dictionary of tensors and plain containers, so a crafted checkpoint cannot run code. It is made in one
place, :func:`make_checkpoint`, from the :class:`RunRecord` (what stays fixed through a run: the
configuration, the model spec, the task, the target and feature scaling, the preprocessing), the model,
the optimiser, the loop state and the RNG states.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from pathlib import Path

import torch

from zernet.inference.model_file import load_checkpoint, model_file
from zernet.io_utils import atomic_save_torch, plain, snapshot_file
from zernet.training.schedule import rng_state

__all__ = [
    "RunRecord",
    "make_checkpoint",
    "save_epoch_checkpoints",
    "save_epoch_weights",
    "epoch_weights_path",
    "load_resume_checkpoint",
    "cpu_state_dict",
]


@dataclass(frozen=True)
class RunRecord:
    """The parts of every checkpoint of a run that do not change from epoch to epoch."""

    config: dict  # RunConfig.to_dict()
    model_spec: dict  # see zernet.inference.spec.model_spec
    task: str  # classification | regression
    num_classes: int | None
    correspondence: bool
    target_stats: dict | None  # see zernet.inference.targets.target_stats
    target_exponent: float  # area exponent of the regression target (predict returns a surface's own units)
    feature_stats: dict | None
    preprocess: dict  # see zernet.training.build.preprocess_spec
    template_faces: torch.Tensor | None = None  # correspondence: (F, 3) faces of the template (refinement)
    # correspondence: (M, 3) float32 vertices of the template, the first training shape as preprocessed
    # (area-normalised): the geometry of the global refinement (training.spectral_refine); older: absent
    template_vertices: torch.Tensor | None = None


def cpu_state_dict(module_or_optimizer) -> dict:
    """A state dict with every tensor copied to the CPU, so the checkpoint loads on any machine."""

    def to_cpu(value):
        if isinstance(value, torch.Tensor):
            return value.detach().to("cpu", copy=True)
        if isinstance(value, dict):
            return {k: to_cpu(v) for k, v in value.items()}
        if isinstance(value, list):
            return [to_cpu(v) for v in value]
        if isinstance(value, tuple):
            return tuple(to_cpu(v) for v in value)
        return value

    return to_cpu(module_or_optimizer.state_dict())


def make_checkpoint(record: RunRecord, model: torch.nn.Module, optimizer: torch.optim.Optimizer, state: dict) -> dict:
    """The checkpoint after an epoch: ``record``, the weights, the optimiser, the loop ``state``, RNG states."""
    return model_file(
        "checkpoint",
        {
            "config": plain(record.config),
            "model_spec": plain(record.model_spec),
            "task": record.task,
            "num_classes": record.num_classes,
            "correspondence": record.correspondence,
            "target_stats": record.target_stats,
            "target_exponent": record.target_exponent,
            "feature_stats": record.feature_stats,
            "preprocess": record.preprocess,
            "template_faces": record.template_faces,
            "template_vertices": record.template_vertices,
            "model": cpu_state_dict(model),
            "optimizer": cpu_state_dict(optimizer),
            "state": copy.deepcopy(state),
            "rng": rng_state(),
        },
    )


def save_epoch_checkpoints(checkpoint: dict, run_dir: Path, improved: bool) -> None:
    """Write ``best.pt`` (if ``improved``), then keep ``last.pt`` as ``previous.pt`` and write ``last.pt``.

    best.pt first: if the process dies between the writes, last.pt still points at the previous epoch,
    and resuming repeats this epoch identically and rewrites best.pt. previous.pt keeps the last.pt of the
    epoch before: should last.pt ever be unreadable, resume falls back to it (:func:`load_resume_checkpoint`).
    """
    if improved:
        atomic_save_torch(checkpoint, run_dir / "best.pt")
    snapshot_file(run_dir / "last.pt", run_dir / "previous.pt")
    atomic_save_torch(checkpoint, run_dir / "last.pt")


def epoch_weights_path(run_dir: Path, epoch: int) -> Path:
    """Where ``train.keep_epochs`` keeps the weights after ``epoch``."""
    return run_dir / "epochs" / f"epoch_{epoch:03d}.pt"


def save_epoch_weights(checkpoint: dict, run_dir: Path, epoch: int) -> None:
    """Keep the checkpoint after ``epoch`` for later evaluation (``train.keep_epochs``): everything
    :func:`load_checkpoint` and evaluation read, without the optimiser and RNG states (a third of the size
    with Adam; resuming uses last.pt)."""
    kept = {key: value for key, value in checkpoint.items() if key not in ("optimizer", "rng")}
    atomic_save_torch(kept, epoch_weights_path(run_dir, epoch))


def load_resume_checkpoint(run_dir: Path) -> tuple[dict, str | None]:
    """The checkpoint to resume from, and a note when it is not ``last.pt``.

    ``last.pt`` is used when it loads. If it is missing or unusable (truncated, corrupt, crafted), the newest
    usable of ``previous.pt`` (the last.pt of the epoch before) and ``best.pt`` is taken instead: training
    from any checkpoint is deterministic, so the final weights are the same, only an epoch is repeated.
    """
    last = run_dir / "last.pt"
    problems: list[str] = []
    try:
        return load_checkpoint(last), None
    except FileNotFoundError:
        problems.append(f"{last} does not exist")
    except ValueError as error:
        problems.append(str(error))
    candidates = []
    for name in ("previous.pt", "best.pt"):
        try:
            candidates.append((load_checkpoint(run_dir / name), run_dir / name))
        except FileNotFoundError:
            pass
        except ValueError as error:
            problems.append(str(error))
    if not candidates:
        if len(problems) == 1 and not last.exists():
            raise FileNotFoundError(f"cannot resume: {last} does not exist (no epoch has finished yet?)")
        raise ValueError(f"cannot resume {run_dir}: no usable checkpoint: " + "; ".join(problems))
    checkpoint, path = max(candidates, key=lambda item: item[0]["state"]["epoch"])
    note = (
        f"{problems[0]}; resuming from {path} (after epoch {checkpoint['state']['epoch']}) instead, "
        "repeating the epochs after it"
    )
    return checkpoint, note
