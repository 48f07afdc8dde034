"""Starting a run from another run's weights (``zernet train ... --init-from RUN``): pretraining, fine-tuning.

A model trained on many shapes (e.g. generated bodies) is a good start for a user with few shapes of their
own. :func:`load_init_source` reads the other run's selected checkpoint (a run folder means its
``best.pt``), and :func:`initialise_from` copies its weights into the new, freshly initialised model:

- every parameter and buffer whose name and shape agree is copied (the convolutions, the input and hidden
  layers);
- the output layer (``output.*``) keeps its fresh initialisation when its shape differs, i.e. when the new
  task has another number of classes (e.g. from correspondence to segmentation, or to another template);
- any other difference (another model family, other widths, another number of input channels, another
  Zernike degree) is a :class:`~zernet.training.config.ConfigError` naming the first parameter that does not
  fit: silently training a half-initialised model would look like a working fine-tune.

The optimiser, the learning-rate schedule, the epoch count and the RNG states start afresh: only weights are
taken. What was taken is returned as a plain dictionary, which the loop keeps in its state (so a resumed run
still reports it), writes to ``train.log`` and to ``metrics.json`` (``init_from``).
"""

from __future__ import annotations

from pathlib import Path

import torch

from zernet.training.checkpoint import checkpoint_path, load_checkpoint
from zernet.training.config import ConfigError

__all__ = ["HEAD_PREFIX", "InitSource", "load_init_source", "initialise_from", "describe"]

#: Parameters under this prefix form the output layer, re-initialised when its shape differs.
HEAD_PREFIX = "output."


class InitSource:
    """The checkpoint a run starts from: its path, the stored model spec and weights, and the epoch."""

    def __init__(self, path: Path, checkpoint: dict):
        self.path = path
        self.model_spec = dict(checkpoint.get("model_spec") or {})
        self.weights: dict[str, torch.Tensor] = checkpoint["model"]
        state = checkpoint.get("state") or {}
        self.epoch = int(state.get("epoch", 0))
        self.task = checkpoint.get("task")
        self.num_classes = checkpoint.get("num_classes")


def load_init_source(run: str | Path) -> InitSource:
    """The weights to start from: ``run`` is a run folder (its ``best.pt``) or a checkpoint file.

    Raises FileNotFoundError (no such folder or file, or a folder without best.pt) or ValueError (not a
    readable zernet checkpoint), both reported by the CLI as one line with exit code 2.
    """
    run = Path(run).expanduser()
    if not run.exists():
        raise FileNotFoundError(f"--init-from: {run} does not exist (give a run folder or a .pt checkpoint)")
    path = checkpoint_path(run)
    checkpoint = load_checkpoint(path)
    if not isinstance(checkpoint.get("model"), dict):
        raise ValueError(f"--init-from: {path} holds no model weights")
    return InitSource(path, checkpoint)


def initialise_from(model: torch.nn.Module, source: InitSource) -> dict:
    """Copy ``source``'s weights into ``model`` (see the module docstring); returns what was done.

    Returns:
        ``{"source": path, "source_epoch": e, "source_model": name, "copied": n, "reinitialised": [names]}``
        with ``copied`` the number of tensors taken and ``reinitialised`` the output-layer tensors kept fresh.

    Raises:
        ConfigError: a tensor other than the output layer's is missing on either side or has another shape.
    """
    target = model.state_dict()
    source_name = source.model_spec.get("name")
    model_name = _registry_name(model)
    prefix = f"--init-from {source.path}"
    missing = [name for name in target if name not in source.weights]
    unexpected = [name for name in source.weights if name not in target]
    if missing or unexpected:
        name = (missing or unexpected)[0]
        side = "the new model has" if missing else "the checkpoint has"
        raise ConfigError(
            f"{prefix}: parameter {name!r} does not fit: {side} it and the other does not "
            f"(checkpoint model {source_name!r}, new model {model_name!r}); start from a run of the "
            "same model family and widths"
        )
    copied, reinitialised = {}, []
    for name, value in target.items():
        stored = source.weights[name]
        if tuple(stored.shape) == tuple(value.shape):
            copied[name] = stored.to(dtype=value.dtype)
        elif name.startswith(HEAD_PREFIX):
            reinitialised.append(name)
        else:
            raise ConfigError(
                f"{prefix}: parameter {name!r} has shape {tuple(stored.shape)} in the checkpoint "
                f"but {tuple(value.shape)} in the new model (only the output layer may differ: "
                "use the same model options, input features and patch degree)"
            )
    model.load_state_dict(copied, strict=False)
    return {
        "source": str(source.path),
        "source_epoch": source.epoch,
        "source_model": source_name,
        "source_task": source.task,
        "source_classes": source.num_classes,
        "copied": len(copied),
        "reinitialised": reinitialised,
    }


def describe(info: dict) -> str:
    """The ``train.log`` line of an initialisation."""
    fresh = ", ".join(info["reinitialised"]) if info["reinitialised"] else "none"
    return (
        f"init-from: {info['copied']} weight tensors from {info['source']} (epoch {info['source_epoch']}, "
        f"model {info['source_model']}); re-initialised: {fresh}"
    )


def _registry_name(model: torch.nn.Module) -> str:
    return type(getattr(model, "module", model)).__name__
