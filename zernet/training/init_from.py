"""Starting a run from another run's weights (``zernet train ... --init-from RUN``): pretraining, fine-tuning.

A model trained on many shapes (e.g. generated bodies) is a good start for a user with few shapes of their
own. :func:`load_init_source` reads the other run's selected checkpoint (a run folder means its
``best.pt``), and :func:`initialise_from` copies its weights into the new, freshly initialised model:

- every parameter and buffer whose name and shape agree is copied (the convolutions, the input and hidden
  layers);
- the output layer (``output.*``) keeps its fresh initialisation when its shape differs, i.e. when the new
  task has another number of classes (e.g. from correspondence to segmentation, or to another template);
- except between two correspondence runs whose templates differ (another vertex order or count, as between
  generated bodies and a user's copy of FAUST; the checkpoint stores its template, ``template_vertices`` and
  ``template_faces``): then each of the new template's vertices takes the output row of the class the
  checkpoint's own model gives that vertex on the new run's training shapes, its softmax summed over
  :data:`VOTING_SHAPES` of them spread over the training split (:func:`carried_head`). A model trained on many
  people then starts the few people's run knowing where every vertex of their template lies, instead of
  learning 6,890 classes again from 8 people. Why the model's own vote rather than a match of the two
  templates: on generated people renumbered, the vote of 8 scans names the exact source vertex for 94 % of
  the template's vertices, zernet's template match for 43 % (``docs/RECIPES.md``);
- any other difference (another model family, other widths, another number of input channels, another
  Zernike degree) is a :class:`~zernet.training.config.ConfigError` naming the first parameter that does not
  fit: silently training a half-initialised model would look like a working fine-tune.

Weights shipped with zernet are named ``pretrained:NAME`` (:data:`PRETRAINED_PREFIX`): the file
``zernet/pretrained/NAME.pt`` with its provenance beside it (``NAME.json``). They hold a *backbone*: every
tensor but the output layer's (:func:`export_backbone`), so the output layer always starts fresh for the new
task and template, also when its shape happens to agree (a template of another vertex order would otherwise
be taken silently); or a correspondence model with its output layer and its template
(``export_backbone(..., with_output=True)``), whose output layer is carried to the new template as above. A
run starts from them with ``train.init_from: pretrained:NAME`` in its configuration (or ``--init-from
pretrained:NAME``).

The optimiser, the learning-rate schedule, the epoch count and the RNG states start afresh: only weights are
taken. What was taken is returned as a plain dictionary, which the loop keeps in its state (so a resumed run
still reports it), writes to ``train.log`` and to ``metrics.json`` (``init_from``).
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable
from pathlib import Path

import numpy as np
import torch

from zernet.inference.batch import Batch, model_basis_orders, model_directional_order
from zernet.inference.model_file import (
    checkpoint_path,
    load_checkpoint,
    model_file,
    pretrained_names,
    pretrained_path,
    read_model_file,
)
from zernet.inference.spec import build_model_from_spec
from zernet.io_utils import atomic_save_torch
from zernet.training.config import ConfigError

__all__ = [
    "HEAD_PREFIX",
    "PRETRAINED_PREFIX",
    "VOTING_SHAPES",
    "voting_shapes",
    "InitSource",
    "load_init_source",
    "initialise_from",
    "carried_head",
    "export_backbone",
    "describe",
]

#: Parameters under this prefix form the output layer, re-initialised when its shape differs.
HEAD_PREFIX = "output."
#: ``pretrained:NAME`` names weights shipped in ``zernet/pretrained/NAME.pt``.
PRETRAINED_PREFIX = "pretrained:"
#: The kinds of model file a run starts from (:mod:`zernet.inference.model_file`): a run's checkpoint, a
#: backbone, or a template model (fine-tuning ``zernet match``'s classifier on bodies of one's own).
_STARTING_KINDS = ("checkpoint", "backbone", "template")
#: Training shapes on which a correspondence checkpoint votes for the output row of each vertex of a new
#: template (:func:`carried_head`): 8 scans of one person name the exact source vertex for 94 % of them.
VOTING_SHAPES = 8


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
        self.feature_stats = checkpoint.get("feature_stats")
        # (vertices (M, 3), faces (F, 3)) of a correspondence model's template, else None.
        vertices, faces = checkpoint.get("template_vertices"), checkpoint.get("template_faces")
        self.template = None if vertices is None or faces is None else (np.asarray(vertices), np.asarray(faces))


def load_init_source(run: str | Path) -> InitSource:
    """The weights to start from: ``run`` is a run folder (its ``best.pt``), a checkpoint file, or a template
    model file (:mod:`zernet.matching.template`: fine-tuning ``zernet match``'s classifier on bodies of one's own).

    Raises FileNotFoundError (no such folder or file, or a folder without best.pt) or ValueError (not a
    readable zernet checkpoint), both reported by the CLI as one line with exit code 2.
    """
    if str(run).startswith(PRETRAINED_PREFIX):
        name = str(run)[len(PRETRAINED_PREFIX) :]
        run = pretrained_path(name)
        if not run.is_file():
            shipped = ", ".join(PRETRAINED_PREFIX + known for known in pretrained_names(("backbone",))) or "none"
            raise FileNotFoundError(f"init-from: no weights named {name!r} ship with zernet (shipped: {shipped})")
    run = Path(run).expanduser()
    if not run.exists():
        raise FileNotFoundError(f"--init-from: {run} does not exist (give a run folder or a .pt checkpoint)")
    path = checkpoint_path(run)
    checkpoint = read_model_file(path, _STARTING_KINDS, "zernet checkpoint")
    if checkpoint["kind"] == "template":  # its network (one output per template vertex) is a classifier's
        checkpoint = {
            "model_spec": checkpoint["model_spec"],
            "model": checkpoint["model"],
            "task": "classification",
            "num_classes": len(checkpoint["template_positions"]),
        }
    if not isinstance(checkpoint.get("model"), dict):
        raise ValueError(f"--init-from: {path} holds no model weights")
    return InitSource(path, checkpoint)


def initialise_from(
    model: torch.nn.Module, source: InitSource, template=None, voters: Iterable = (), device=None
) -> dict:
    """Copy ``source``'s weights into ``model`` (see the module docstring); returns what was done.

    ``template``: (vertices, faces) of the new run's template when it is a correspondence run, else None;
    ``voters``: that run's training records (read only when the output layer is carried to the template:
    :func:`carried_head`), voting on ``device`` (default CPU).

    Returns:
        ``{"source": path, "source_epoch": e, "source_model": name, "copied": n, "reinitialised": [names],
        "head": how the output layer was set}`` with ``copied`` the number of tensors taken and
        ``reinitialised`` the output-layer tensors kept fresh.

    Raises:
        ConfigError: a tensor other than the output layer's is missing on either side or has another shape.
    """
    target = model.state_dict()
    source_name = source.model_spec.get("name")
    model_name = _registry_name(model)
    prefix = f"--init-from {source.path}"
    backbone = not any(name.startswith(HEAD_PREFIX) for name in source.weights)  # shipped: no output layer
    missing = [
        name for name in target if name not in source.weights and not (backbone and name.startswith(HEAD_PREFIX))
    ]
    unexpected = [name for name in source.weights if name not in target]
    if missing or unexpected:
        name = (missing or unexpected)[0]
        side = "the new model has" if missing else "the checkpoint has"
        raise ConfigError(
            f"{prefix}: parameter {name!r} does not fit: {side} it and the other does not "
            f"(checkpoint model {source_name!r}, new model {model_name!r}); start from a run of the "
            "same model family and widths"
        )
    weights, head = dict(source.weights), "copied" if not backbone else "fresh (a backbone)"
    if (
        not backbone
        and template is not None
        and source.template is not None
        and not _same_mesh(template, source.template)
    ):
        rows, votes = carried_head(source, voters, len(template[0]), device)
        voted = torch.as_tensor(votes > 0)
        for name in [name for name in weights if name.startswith(HEAD_PREFIX)]:
            carried = target[name].clone()  # a vertex no training shape votes for keeps its fresh row
            carried[voted] = weights[name][torch.as_tensor(rows)[voted]].to(carried.dtype)
            weights[name] = carried
        head = (
            f"carried from the checkpoint's template ({len(source.template[0])} vertices) by its model's vote "
            f"on {int(votes.max(initial=0))} training shapes; {int((~voted).sum())} vertices without a vote kept "
            "a fresh row"
        )
    copied, reinitialised = {}, []
    for name, value in target.items():
        stored = weights.get(name)
        if stored is None:  # a backbone's output layer: fresh
            reinitialised.append(name)
        elif tuple(stored.shape) == tuple(value.shape):
            copied[name] = stored.to(dtype=value.dtype)
        elif name.startswith(HEAD_PREFIX):
            reinitialised.append(name)
            head = "fresh (another number of outputs)"
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
        "head": head,
    }


def _same_mesh(one, other) -> bool:
    """Whether two (vertices, faces) templates share their connectivity (then their vertices correspond)."""
    return one[1].shape == other[1].shape and bool(np.array_equal(one[1], other[1]))


def voting_shapes(train_indices) -> list:
    """The training shapes that vote in :func:`carried_head`: :data:`VOTING_SHAPES` of ``train_indices``
    spread evenly over them (FAUST's consecutive scans are one person)."""
    spread = np.linspace(0, len(train_indices) - 1, min(VOTING_SHAPES, len(train_indices))).round().astype(int)
    return [train_indices[i] for i in dict.fromkeys(spread.tolist())]


def carried_head(source: InitSource, voters: Iterable, num_classes: int, device=None) -> tuple[np.ndarray, np.ndarray]:
    """For each class of a new correspondence run (a vertex of its template), the class of ``source`` whose
    output row it starts from: the one ``source``'s model gives the training vertices of that class, its
    softmax summed over the first :data:`VOTING_SHAPES` records of ``voters`` (the run's training shapes,
    each target the template vertex of every vertex).

    Returns:
        rows: (num_classes,) int64 source class per class (0 where no vertex voted).
        votes: (num_classes,) int64 number of shapes that voted for each class (0: keep a fresh row).
    """
    device = torch.device(device or "cpu")
    model = build_model_from_spec(source.model_spec)
    model.load_state_dict({name: value.float() for name, value in source.weights.items()})
    model.to(device).eval()
    directional, basis_orders = model_directional_order(model), model_basis_orders(model)
    scores = torch.zeros(num_classes, source.weights[HEAD_PREFIX + "weight"].shape[0], device=device)
    votes = torch.zeros(num_classes, dtype=torch.int64)
    with torch.no_grad():
        for record in itertools.islice(voters, VOTING_SHAPES):
            batch = Batch([record], device, None, source.feature_stats, directional, basis_orders)
            target = torch.as_tensor(record.target, dtype=torch.int64, device=device)
            scores.index_add_(0, target, torch.softmax(model(batch.features, batch.geometry).float(), dim=1))
            votes[torch.unique(target).cpu()] += 1
    return scores.argmax(dim=1).cpu().numpy(), votes.numpy()


def export_backbone(run: str | Path, path: str | Path, with_output: bool = False) -> dict:
    """Write the backbone of ``run``'s selected model (a run folder or checkpoint file) to ``path``: a
    checkpoint of every weight but the output layer's (``with_output``: every weight, for a correspondence
    model whose template the checkpoint stores), in float16 (half the size; a model starting from it trains
    in its own precision), with the run's configuration and model spec and without its optimiser.
    Returns what was written: ``{"tensors": n, "parameters": p, "bytes": b}``."""
    source = load_checkpoint(checkpoint_path(Path(run).expanduser()))
    if with_output and (source.get("template_vertices") is None or source.get("template_faces") is None):
        raise ValueError(f"{run}: only a correspondence model that stores its template ships its output layer")
    weights = {
        name: value.half() if value.is_floating_point() else value
        for name, value in source["model"].items()
        if with_output or not name.startswith(HEAD_PREFIX)
    }
    dropped = ("optimizer", "rng", "model", "format", "version", "kind")
    kept = model_file("backbone", {key: value for key, value in source.items() if key not in dropped})
    kept["model"] = weights
    atomic_save_torch(kept, Path(path))
    return {
        "tensors": len(weights),
        "parameters": int(sum(value.numel() for value in weights.values())),
        "bytes": Path(path).stat().st_size,
    }


def describe(info: dict) -> str:
    """The ``train.log`` line of an initialisation."""
    fresh = ", ".join(info["reinitialised"]) if info["reinitialised"] else "none"
    return (
        f"init-from: {info['copied']} weight tensors from {info['source']} (epoch {info['source_epoch']}, "
        f"model {info['source_model']}); re-initialised: {fresh}; output layer: {info.get('head', 'copied')}"
    )


def _registry_name(model: torch.nn.Module) -> str:
    return type(getattr(model, "module", model)).__name__
